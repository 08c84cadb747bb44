"""PH-Dropout core library: cameras, data, renderers, trainers, PH-Dropout and metrics.

Pure library: nothing here imports web code.
"""

__version__ = "0.1.0"
