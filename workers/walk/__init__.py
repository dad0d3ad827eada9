"""The walk: torch kernels of one photon random walk and its estimators.

Counter-based random numbers (rng), interface optics and the phase function (optics), the lanes
and their step (walk), the estimators (harvest: the exit tally; connections; hybrid), the torch
bin lookups (binning) and the compile-ahead machinery (kernels, engine). The physics conventions
every module of the library follows are written in conventions. Nothing here imports the fold.
"""
