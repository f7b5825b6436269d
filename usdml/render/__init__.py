"""The render delegate: per-frame passes (G-buffer, direct lighting) and sequences of frames to EXR."""
