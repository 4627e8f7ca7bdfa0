"""Policies that drive pursuers: the interface, rule-based teammates and the zoos."""

from atdrone.envs.kinematics import turn_towards
from atdrone.policies.base import DroneBatch, Policy, StatelessPolicy
from atdrone.policies.rules import GreedyPolicy, VicsekPolicy, chase_nearest

__all__ = [
    "DroneBatch",
    "GreedyPolicy",
    "Policy",
    "StatelessPolicy",
    "VicsekPolicy",
    "chase_nearest",
    "turn_towards",
]
