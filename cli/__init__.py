"""The ``terrainmap`` command line (installed as :mod:`terrainmap.cli`): a thin layer over the library."""
