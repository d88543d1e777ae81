"""Scenario builders for the tests and benchmarks: takes, sim rigs' pieces, synthetic scenes and
event streams with known truth.

Only tests and benches import this package; runtime code never does (it may use the simulator).
What runs a capture through the app lives in `rigd.app.testing`, what drives a device contract
in `drivers.testing`.

- `board`: the sim's moving board: its spec, the sim's true intrinsics, e2calib scored on a take
- `board_views`: board images rendered through a known camera (calibration ground truth)
- `stereo`: a finalized two-camera take of the board with known intrinsics and baseline
- `sprites`: textured sprites moving over a background, their events from the pixel model
- `takes`: small synthetic takes written through `TakeWriter` (events, frames, triggers, pulses)
- `wire`: pulses fired on a sim world's trigger wire
- `frames`: folders of frames for `rigd simulate-events`
"""
