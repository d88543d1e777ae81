"""Scenario builders that go through the app, for the tests and benchmarks: sim rig configs,
captures of the moving board, daemons and the web console on small sim rigs, and takes written
as a crashed capture leaves them.

Only tests and benches import this package; the app itself never does. It is the one place in
`rigd` that may reach the simulator (`firmware_sim.testing`, for a world's reset and the board's
truth): the import-linter contract names it as the exception.

- `board`: the sim rig watching the moving board, and a capture of it
- `daemon`: a small sim rig's config, a daemon in a thread or a process, its endpoints
- `console`: a daemon with the web console attached
- `crash`: a one-camera, one-sensor writer and the data of each pulse (recovery, damaged takes)
"""
