"""Synthetic turntable scenes with exact ground truth (``turntable synth``)."""
