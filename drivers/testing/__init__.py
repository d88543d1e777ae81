"""Contract suites every backend runs, in the style of python-microscope's testsuite.

Each suite is a class of pytest tests; a backend's test module mixes it into a test class and
provides the fixtures the suite's docstring names (an opened, stopped device, and a way to make
it produce data). Only tests import this package: it imports pytest.
"""
