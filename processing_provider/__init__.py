"""QGIS Processing provider of gdal_gf4cal (provider id ``gf4cal``).

A thin layer over the engine :mod:`gdal_gf4cal`: each algorithm (one module under :mod:`.algorithms`) reads its
parameters, calls one engine function with a progress/cancel adapter and returns a dict of outputs. Engine errors
become ``QgsProcessingException`` in one place (:class:`.base.Gf4calAlgorithm`). Nothing here draws GUI, so the
provider works in ``qgis_process`` and headless PyQGIS.

``make plugin`` packages this folder with a vendored copy of the engine as the QGIS plugin ``gdal_gf4cal_plugin``.
"""
