"""tirdeflect application: acquisition, buffers, recording, CLI and GUI."""
