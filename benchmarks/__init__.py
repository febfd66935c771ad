"""Benchmarks of the Drake closed loop against a hand-written numpy baseline.

Run ``python -m benchmarks [--quick] [--out FILE.json]`` from the repository
root; see ``benchmarks/RESULTS.md`` for the numbers on the reference machine.

Modules: :mod:`benchmarks.fused_numpy` (the baseline), :mod:`benchmarks.cases`
(scenario variants and the reference solution), :mod:`benchmarks.suite` (the
sections), :mod:`benchmarks.timing` (statistics, machine description) and
:mod:`benchmarks.report` (targets and tables).
"""
