"""terrainmap.sinks."""
