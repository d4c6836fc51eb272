"""terrainmap.sources."""
