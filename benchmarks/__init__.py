"""Benchmarks of the Drake closed loop against hand-written numpy baselines.

Run ``python -m benchmarks [--quick] [--out FILE.json] [--markdown FILE.md]``
from the repository root; see ``benchmarks/RESULTS.md`` for the numbers on
the reference machine.

Modules: :mod:`benchmarks.precomputed_numpy` (the stronger baseline, the
targets' yardstick) and :mod:`benchmarks.fused_numpy` (the fused one, the
second column), :mod:`benchmarks.cases` (scenario variants and the reference
solution), :mod:`benchmarks.suite` (the comparison sections),
:mod:`benchmarks.evaluation` (one evaluation split by block),
:mod:`benchmarks.scaling` (the cart-pole scaling rows; the n = 6 scenario is
in ``benchmarks/scenarios/``), :mod:`benchmarks.sweep` (``ablate``
throughput), :mod:`benchmarks.timing` (statistics, machine description) and
:mod:`benchmarks.report` (targets and tables); :mod:`benchmarks.learning_table`
is the learning table of ``docs/learning.md``.
"""
