"""The application: solving, outputs, the pipeline that wires the stages, and the command line."""
