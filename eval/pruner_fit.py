"""Moved to :mod:`tts.training`. Only tests/test_imagenet.py still imports ``read_grid`` from here:
delete this file once it imports ``from tts.training import read_grid``."""
from tts.training import read_grid  # noqa: F401
