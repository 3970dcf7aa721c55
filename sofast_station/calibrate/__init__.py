"""Calibration routines: the daily radiometric calibration, camera intrinsics, station geometry; the
records they write and the checks that decide whether a record may still be used (docs/calibration.md).

Modules are imported on demand (``from sofast_station.calibrate.radiometric import calibrate_radiometric``);
none imports the digital twin.
"""
