"""Acquisition and recording: camera thread, ring buffer, HDF5 recorder, trigger,
the live processing worker and the synthetic tank scene."""
