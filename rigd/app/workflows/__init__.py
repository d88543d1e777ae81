"""Live workflows as plain library calls: guided calibration with the rig's own devices.

The CLI command and the web console both call these; so they take typed options, return typed
results, report progress through a callback and raise `RigdError`s, and never print. Offline
work on finished takes lives one layer down, in `rigd.products`.
"""
