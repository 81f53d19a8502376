"""Camera rigs as Mitsuba 3 scene XML (installed as ``elicit_diffrender.scenes``)."""
