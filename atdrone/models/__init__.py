"""The maths of a policy: networks, per-drone memory, the checkpoint format (below policies and learning)."""
