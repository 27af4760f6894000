"""The matrix kernel of the engine: per-frame tables, a 3x3 matrix per frame, integer shifts.

:func:`merge_matrix_frames` runs :func:`derender.engine.kernels.stabilized_merge_rows`
(numba, rows in ``prange``): image ``j`` contributes ``M_j L_j(z)`` (per-channel table
``L_j`` on the 256 codes, 3x3 ``M_j``) read through its registration shift, with one weight
for all channels (the smallest channel weight where some exposure has all channels
usable, else the weight of the brightest channel) optionally times an inverse-variance
table. Launches are serialised by :data:`KERNEL_LOCK` (numba's fallback thread pool
cannot run two parallel kernels at once).
"""

from __future__ import annotations

import threading

import numpy as np

from derender.core.memory import N_CODES, thread_count

__all__ = [
    "stabilized_output_bytes",
    "KERNEL_LOCK",
    "set_numba_threads",
    "warm_up_kernels",
]


def stabilized_output_bytes(h: int, w: int) -> int:
    """Bytes of the stabilised merge's outputs: planar float32 radiance and a uint8 mask."""
    return 13 * int(h) * int(w)


#: Serialises launches of the parallel numba kernels (see :mod:`derender.kernels`).
KERNEL_LOCK = threading.Lock()


def set_numba_threads(threads: int | None) -> None:
    import numba

    numba.set_num_threads(max(1, min(thread_count(threads), int(numba.config.NUMBA_NUM_THREADS))))


def warm_up_kernels() -> threading.Thread:
    """Import numba and load the MTB and merge kernels from its cache (0.5-1 s) in a
    background thread while the frames decode: the import holds the GIL, decoding
    (libjpeg-turbo) does not. Failures are left for the real calls to report."""
    def run() -> None:
        try:
            from derender.engine.kernels import mtb_band_counts, stabilized_merge_rows

            mtb_band_counts(np.zeros((1, 1), np.uint8), np.zeros((1, 1), np.uint8), 0, 0, 4, np.zeros(1, np.int64),
                            1, 0, np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros((1, 2), np.int64))

            f32 = np.float32
            with KERNEL_LOCK:
                stabilized_merge_rows(np.zeros((1, 1, 1, 3), np.uint8), np.zeros((1, 2), np.int64),
                                      np.ones((1, 1, 1), np.uint8), np.zeros((1, N_CODES, 3), f32),
                                      np.zeros((1, 3, 3), f32), np.zeros((1, 3, 3)), np.zeros((N_CODES, 3), f32),
                                      np.zeros((1, N_CODES, 3), f32), np.ones(1, f32), True, 0, 0,
                                      np.zeros(N_CODES, bool), 0, 1, np.zeros((3, 1, 1), f32),
                                      np.zeros((1, 1), np.uint8))
        except Exception:  # noqa: BLE001
            pass

    th = threading.Thread(target=run, name="derender-warm-up", daemon=True)
    th.start()
    return th
