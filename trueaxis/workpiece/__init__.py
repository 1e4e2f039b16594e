"""The workpiece (layer 4; docs/architecture.md): the test parts (CAD, analytic surfaces, probe pattern, description
JSON) and their tool paths. Imports ``nc``, ``machine`` and the base modules only."""
