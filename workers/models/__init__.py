"""Analytic and tabulated models the exports use: photon beam diffusion (diffusion), Catmull-Rom
splines (catmull_rom) and the tabulated profiles built from them (tabulated). No torch."""
