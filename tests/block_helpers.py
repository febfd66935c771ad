"""Helpers shared by the block tests (Python and symbolic)."""

import numpy as np

from ofrl_drake.observer import ObserverGains


def ports(system):
    ins = {
        system.get_input_port(i).get_name(): system.get_input_port(i).size()
        for i in range(system.num_input_ports())
    }
    outs = {
        system.get_output_port(i).get_name(): system.get_output_port(i).size()
        for i in range(system.num_output_ports())
    }
    return ins, outs


def random_gains(system, seed=0):
    rng = np.random.default_rng(seed)
    n, m, q = system.n, system.m, system.q
    Mg1 = -rng.uniform(0, 2, (n, n, m))
    return ObserverGains.from_arrays(
        system,
        L=rng.normal(size=(n, q)),
        H=rng.normal(size=(n, q)),
        K=rng.normal(size=(n, q)),
        Mf1=rng.normal(size=(n, n)),
        Mg1=Mg1,
        Mg2=Mg1 + rng.uniform(0, 3, (n, n, m)),
    )
