"""The protocol's rotation convention, as code: a unit quaternion ``(w, x, y, z)`` (scalar first,
``protocol/SPEC.md``) turns a frame's coordinates into the world's. Both sides of the wire use
this one function: the server's model kernels and the clients' narrow phase jit it with numba
(plain indexing and arithmetic only, so it compiles as it is); Python callers use it directly.
No numba here: importing the protocol stays light."""
from __future__ import annotations


def quat_to_matrix_into(q, R):
    """Rotation matrix (frame to world) of the unit quaternion ``q = (w, x, y, z)`` into ``R``
    (3x3); returns ``R``."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    R[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[0, 1] = 2.0 * (x * y - z * w)
    R[0, 2] = 2.0 * (x * z + y * w)
    R[1, 0] = 2.0 * (x * y + z * w)
    R[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[1, 2] = 2.0 * (y * z - x * w)
    R[2, 0] = 2.0 * (x * z - y * w)
    R[2, 1] = 2.0 * (y * z + x * w)
    R[2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return R
