"""terrainmap.sim."""
