"""The method's stages, one module (or subpackage) each, in pipeline order: primitives, visibility, fusion,
language_field, masks, neighbors, superprimitives, affinity, clustering, labeling, export (docs/architecture.md).

The appearance stage (the Gaussian scene) is its own package, :mod:`panogs_core.gaussians`.
"""
