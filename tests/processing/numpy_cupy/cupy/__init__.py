"""NumPy under the name ``cupy``, with the few ``cupy.cuda`` calls that
benchmarks/gpu_check.py and processing/gpu.py make: put this folder's parent on
PYTHONPATH to run that script's whole flow without a GPU (a dry run of the
script, not of CuPy: the figures it prints are NumPy's). Used by
tests/processing/test_gpu.py only.
"""

import types

import numpy as _np
from numpy import *  # noqa: F401,F403 - the array API the chain uses (xp.matmul, xp.angle...)

fft = _np.fft


def asnumpy(array, out=None):
    if out is None:
        return _np.asarray(array)
    out[...] = array
    return out


class _Device:
    id = 0

    def synchronize(self):
        pass


class _Runtime:
    @staticmethod
    def getDeviceCount():
        return 1

    @staticmethod
    def getDeviceProperties(index):
        return {"name": b"NumPy stand-in (dry run, no GPU)"}


cuda = types.SimpleNamespace(runtime=_Runtime, Device=_Device)
