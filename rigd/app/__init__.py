"""The application: rig config, capture sessions, the daemon service and the command line.

Only this package wires the libraries together (drivers, the take file, the sync engine,
calibration, reconstruction); none of them imports it (see the import-linter contracts in
pyproject.toml).
"""
