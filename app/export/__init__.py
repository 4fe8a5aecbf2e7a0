"""Writers that take a calibration to the tools its users work in (simulators, SfM/VIO, hand-eye).

One module per target family, each written from one `CameraModel`; `targets.export_camera` picks
the writer for `calibcoach export --to TARGET`. Each module's docstring says what its formats hold
exactly and what they approximate.
"""
