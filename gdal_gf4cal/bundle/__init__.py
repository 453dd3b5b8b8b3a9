"""Bundle adjustment of separate views from their RPCs (METHODS §11; issue 22).

Stereo, tri-stereo and multi-date views brought into one frame from tie points: a correction per view in image
space (the bases of ``refine``, METHODS §4.1), tie points as 3-D unknowns eliminated by Schur complement, the datum
held by a prior per view (or GCPs), robust on whole rays through the core's driver::

    from gdal_gf4cal.bundle import adjust_views, BundleEstimate, corrected_models
    est = adjust_views(observations, models, dem=None, model="affine")
    models_after = corrected_models(est, models)

Modules: :mod:`.model` (views, parameters, rays), :mod:`.inputs` (checks and arrays), :mod:`.start` (starting
ground, a-priori weights), :mod:`.solve` (Gauss-Newton with Schur elimination), :mod:`.adjust` (the entry point
and the driver's problem), :mod:`.result` (:class:`BundleEstimate`, reprojection, corrected models).
"""
from .adjust import BundleProblem, adjust_views
from .model import BUNDLE_MODELS, DEFAULT_PRIOR_M, DEFAULT_PRIOR_PX, MIN_SPAN, BundleError
from .result import BundleEstimate, corrected_models, reprojection
from .start import DEFAULT_DEM_SIGMA_M

__all__ = ["adjust_views", "BundleEstimate", "corrected_models", "BundleProblem", "BundleError", "BUNDLE_MODELS",
           "DEFAULT_PRIOR_M", "DEFAULT_PRIOR_PX", "DEFAULT_DEM_SIGMA_M", "MIN_SPAN", "reprojection"]
