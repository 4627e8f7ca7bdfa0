"""The maths of a policy: networks, per-drone memory, the checkpoint format (below policies and learning)."""

from atdrone.models.architectures import ARCHITECTURES, CheckpointError, PolicyModel, build_model
from atdrone.models.history import DroneMemory

__all__ = ["ARCHITECTURES", "CheckpointError", "DroneMemory", "PolicyModel", "build_model"]
