"""terrainmap.evaluation."""
