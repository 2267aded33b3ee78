"""keyvision: keypoint estimators and renderers that learn cldyn dynamics from images."""

import importlib.metadata

from ._data import (
    Frames as Frames,
    PlanarCamera as PlanarCamera,
    cache_directory as cache_directory,
)
from ._estimator import (
    AbstractKeypointEstimator as AbstractKeypointEstimator,
    KeypointEstimator as KeypointEstimator,
    KeypointEstimatorFC as KeypointEstimatorFC,
)
from ._evaluate import keypoint_tracking as keypoint_tracking, pose_features as pose_features
from ._keypoints import (
    frame_to_pixel as frame_to_pixel,
    gaussian_maps as gaussian_maps,
    pixel_grid as pixel_grid,
    pixel_to_frame as pixel_to_frame,
    spatial_softmax as spatial_softmax,
)
from ._render import RenderProtocol as RenderProtocol, render as render
from ._renderer import (
    AbstractRenderer as AbstractRenderer,
    Renderer as Renderer,
    RendererFC as RendererFC,
)

try:
    __version__ = importlib.metadata.version("cldyn")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"
