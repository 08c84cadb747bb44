"""Trainers: the fit loops that turn a dataset into a model: `splats` (the loop every splat
family shares), `gs3d` and `gs2d` (its recipes), `nerf`.

Only `phd train` (through each family's `trainer` name), the demo and the benchmarks
import them; loading or rendering a model never does.
"""
