"""The local model of interaction (server side): numba kernels over preallocated arrays."""
from .model import ContactParams, ContactSnapshot, LocalModel, ToolSpec, warm_up

__all__ = ["ContactParams", "ContactSnapshot", "LocalModel", "ToolSpec", "warm_up"]
