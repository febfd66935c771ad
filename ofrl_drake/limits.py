"""Limits on counts of work: the most checkpoints, initial states and runs one call takes.

Each unit of these counts costs a closed-loop simulation (and for an initial
state of an ablation, a direct-collocation ``J*`` solve), so a count past its
limit would take gigabytes or days before anything is written. The library
refuses it (:func:`ofrl_drake.checks.count_at_most`), naming the value, the
limit and what to do instead; the command line refuses it while parsing its
arguments. Each limit is far above real use.
"""

from __future__ import annotations

__all__ = [
    "CHECKPOINTS_FIX",
    "INITIAL_STATES_FIX",
    "MAX_CHECKPOINTS",
    "MAX_INITIAL_STATES",
    "MAX_RUNS",
    "RUNS_FIX",
]

#: Most checkpoints of a learning curve (``run --checkpoints``): each is one more
#: closed-loop simulation over the whole horizon (milliseconds to seconds), so 10^4
#: already take minutes to hours, against a default of 10; a billion would allocate
#: 8 GB for the checkpoint times alone, before ``max_wall_time`` could act.
MAX_CHECKPOINTS = 10_000

#: What the refusal of more than :data:`MAX_CHECKPOINTS` suggests.
CHECKPOINTS_FIX = "a learning curve needs far fewer checkpoints (default 10)"

#: Most initial states an ablation draws (``ablate --initial-states``): each adds a
#: run of every variant and a direct-collocation ``J*`` solve (seconds), so 10^4
#: states are about a day of CPU, far above the handful a sweep uses; a billion took
#: 16 GB before the first run.
MAX_INITIAL_STATES = 10_000

#: What the refusal of more than :data:`MAX_INITIAL_STATES` suggests.
INITIAL_STATES_FIX = "split the sweep into several --out folders with other --seed values"

#: Most runs of one Monte Carlo sweep (``montecarlo --runs``): each is a closed-loop
#: simulation (about a second on the cart-pole) and a file in ``runs/``, and the
#: envelope figure holds every run's trajectory in memory (10^4 cart-pole runs: about
#: 0.4 GB), far above the tens a study uses; a billion ran out of memory.
MAX_RUNS = 10_000

#: What the refusal of more than :data:`MAX_RUNS` suggests.
RUNS_FIX = "split the sweep into several --out folders (--seed S runs seeds S, S + 1, ...)"
