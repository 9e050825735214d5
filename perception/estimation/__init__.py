"""Estimators on point clouds: ICP and its face grid, PAH acquisition, the seed-003 line tracker,
the outline (silhouette) refinement and the adaptive voxel grid.

Above ``perception.sensing`` and the models; below ``perception.pipeline``.
"""
