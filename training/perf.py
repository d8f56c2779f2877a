"""Process-level performance settings for long training runs (public: the CLIs and studies call them).

Call both once at the start of a long training process (``train``, ``training.bench``, the image
inverse study): ``tune_malloc()`` then ``set_threads(n)``.

Batched training allocates and frees the same few large temporaries every
epoch.  With glibc's defaults, blocks above the (dynamic) mmap threshold go
back to the kernel on ``free`` and come back as fresh zero pages, and the
page faults cost more than the arithmetic.  :func:`tune_malloc` raises the
mmap and trim thresholds so freed blocks are reused (measured ~1.5x faster
Gauss–Newton matrices on the 2-core development machine).  It only changes
allocator policy, never results, and is a no-op off glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util


def tune_malloc() -> bool:
    """Raise glibc's mmap / trim thresholds (see the module docstring); True when glibc accepted them."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
    ok = bool(mallopt(M_MMAP_THRESHOLD, 32 << 20))  # glibc's maximum
    ok &= bool(mallopt(M_TRIM_THRESHOLD, 1 << 30))
    ok &= bool(mallopt(M_TOP_PAD, 64 << 20))
    return ok


def set_threads(threads: int | None) -> int:
    """Torch intra-op threads (``0``/None = torch's default); with an explicit count the BLAS
    libraries loaded next to torch (scipy's OpenBLAS, used for LM's Cholesky steps) get the
    same limit, so worker processes do not oversubscribe the cores."""
    from elastimap.errors import UserError

    if threads is not None and (isinstance(threads, bool) or int(threads) != threads or threads < 0):
        raise UserError("threads", f"must be an integer >= 0 (0 = torch's default; got {threads})")
    import torch

    if threads:
        torch.set_num_threads(int(threads))
        from scipy.linalg import lapack  # noqa: F401  (load scipy's BLAS so the limit reaches it)
        from threadpoolctl import threadpool_limits

        threadpool_limits(int(threads), user_api="blas")
    return torch.get_num_threads()
