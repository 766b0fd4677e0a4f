"""Orchestration in numpy/scipy: events -> packets -> omega -> spline -> BA -> map.

Installed as ``ti_cmax.pipelines``. Pipelines hold the decisions; kernels hold the math.
"""
