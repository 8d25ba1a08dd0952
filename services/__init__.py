"""The pipeline's stages, one folder each: pure algorithms plus one thin Zenoh node."""
