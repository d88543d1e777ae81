"""Take products: what is made from a finished take, offline (calibrate, export, reconstruct,
inspect, convert).

Each is a plain library call on take files: typed options, typed results, progress through a
`rigd.core.progress` callback, `RigdError`s raised, nothing printed. They touch no live device
and nothing of the application above (the CLI, the daemon, the console call them), so a
training or batch job can use them without the rig. Import the submodule you need: each pulls
in its own heavy dependencies (OpenCV, dask).
"""
