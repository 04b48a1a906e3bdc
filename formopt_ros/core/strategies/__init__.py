"""Every motion strategy behind one interface: ``plan(problem, rng, **options) -> Plan``."""
from __future__ import annotations

from typing import Callable

from formopt_ros.core.strategies.baselines import plan_crm, plan_gbs, plan_mme, plan_mtf
from formopt_ros.core.strategies.common import Plan
from formopt_ros.core.strategies.ram import plan_ram
from formopt_ros.core.strategies.rq import plan_rq

#: name -> (planner, accepted keyword options)
STRATEGIES: dict[str, tuple[Callable[..., Plan], frozenset[str]]] = {
    'mtf': (plan_mtf, frozenset()),
    'crm': (plan_crm, frozenset()),
    'mme': (plan_mme, frozenset({'step', 'leader_straight'})),
    'gbs': (plan_gbs, frozenset({'cell'})),
    'ram': (plan_ram, frozenset({'fallback'})),
    'rq': (plan_rq, frozenset()),
}

__all__ = ['STRATEGIES', 'Plan']
