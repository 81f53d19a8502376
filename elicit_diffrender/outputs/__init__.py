"""What a fitted run turns into: ``video`` (free-view and animation videos, contact sheets), ``evaluate``
(metrics against a subject's other views), ``export`` (an animated glTF binary), ``surface`` (where a soft
volume's surface lies), ``texture`` (its UV atlas and the texture baked from the radiance field) and ``viewer``
(a self-contained web page of it).

May import: ``model``, ``data``, ``body``, ``core``. Not ``inputs`` or ``fit`` (siblings).
"""
