"""Demonstrations for training: `dojo collect`, one HDF5 file per episode, and LeRobot v3 datasets."""
