"""The batch engine: recordings and image files to heights in HDF5.

``tirdeflect process``, the GUI's export and scripts all call :func:`run_process`.
"""

from app.batch.engine import BatchReport, ProcessJob, run_process

__all__ = ["ProcessJob", "BatchReport", "run_process"]
