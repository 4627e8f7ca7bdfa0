"""Policies that drive pursuers: the interface, rule-based teammates and the zoos."""

from atdrone.policies.base import DroneBatch, Policy, StatelessPolicy, turn_towards
from atdrone.policies.rules import GreedyPolicy, VicsekPolicy

__all__ = ["DroneBatch", "GreedyPolicy", "Policy", "StatelessPolicy", "VicsekPolicy", "turn_towards"]
