"""Trainers: the fit loops that turn a dataset into a model (`gs3d`, `nerf`).

Only `phd train` (through each family's `trainer` name), the demo and the benchmarks
import them; loading or rendering a model never does.
"""
