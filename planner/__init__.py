"""planner: raster planning (CasADi), localization, and the `palpate` CLI. Importing the package imports nothing heavy."""
