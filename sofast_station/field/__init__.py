"""The heliostat in the field, seen from the tower's camera (docs/field.md).

Pure math, numpy in and numpy out:

geometry
    The field frame (x east, y north, z up, metres), a heliostat's orientation (azimuth, elevation, spin)
    and the tower camera's pointing.
sun
    The sun's position from pvlib, and the normal a heliostat is commanded to (the bisector of the sun and
    its aim point).
detect
    Facet corners by edge detection in a photograph of a heliostat seen from far away.
orientation
    The heliostat's normal and tracking error from one photograph, with U (k = 2).
canting
    Every facet's corners in 3-D by bundle adjustment over several photographs, each facet's normal and
    canting error with U, and the comparison with the factory's record of the same serial.
prescription
    The canting a heliostat's place in the field asks for (on axis at its slant range, or off axis for a
    moment), as a design the line measures against.

Files and the command: ``inputs`` (the site file, the field layout, photographs and their notes),
``picture`` (the PNGs people look at), ``cli`` (``sofast-station field ...``); ``study`` runs the
population study on the twin (``sofast_station.twin.field``).
"""
