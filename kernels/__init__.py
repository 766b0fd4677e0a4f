"""Taichi kernels: math only (warps, voting, contrast gradients, spline poses, rendering).

Installed as ``ti_cmax.kernels``. Every module imports Taichi through :mod:`.runtime`
and ships a numpy twin of each kernel used as a test oracle.
"""
