"""Simulated rig: trigger-box firmware on a pseudo-terminal, cameras, event sensors, scenes.

Runtime code never imports this package; the daemon reaches the `sim://` backends through
the `rigd.backends` entry points, exactly as it would reach a third-party backend.
"""
