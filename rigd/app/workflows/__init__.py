"""Use cases of the application as plain library calls: calibrate, reconstruct, guided calibration.

The CLI commands, the daemon and a web page all call these; so they take typed options, return
typed results, report progress through a callback and raise `RigdError`s, and never print.
Import the submodule you need: each pulls in its own heavy dependencies.
"""
