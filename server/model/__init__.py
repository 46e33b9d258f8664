"""The local model of interaction (server side): numba kernels over preallocated arrays."""
from .model import ContactParams, ContactSnapshot, LinkSpec, LocalModel, ToolSpec, linkage_dims, warm_up

__all__ = ["ContactParams", "ContactSnapshot", "LinkSpec", "LocalModel", "ToolSpec", "linkage_dims", "warm_up"]
