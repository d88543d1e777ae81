"""The web console of `rigd serve`: live dashboard, take controls and guided calibration.

app.py holds the routes, security.py who may do what, live.py the rate-limited latest-value
publishing, takes.py the take list, calibrate.py the guided calibration, server.py the uvicorn
thread; the pages are plain files under static/ (no build step).
"""
