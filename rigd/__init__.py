"""rigd: capture daemon for a hybrid RGB + event-camera multi-view rig.

Kept import-light on purpose: `drivers`, `calibration` and `reconstruction` import
`rigd.core`, which would otherwise drag the daemon in with it.
"""

__version__ = "0.1.0"
