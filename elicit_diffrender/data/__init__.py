"""What a fit is given and seen through: subject folders, motions, camera rigs, and Mitsuba renders of meshes.

``subject`` (the ``elicit-subject/1`` folder), ``motions`` (pose sequences), ``rigs`` (camera rigs as Mitsuba
scene XML, placed around a body), ``mesh_render`` (Mitsuba renders of a posed mesh: colour, masks, part labels,
depth, path-traced shading).

May import: ``body``, ``core``.
"""
