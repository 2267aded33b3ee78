"""keyvision: keypoint estimators and renderers that learn cldyn dynamics from images."""

import importlib.metadata

from ._assign import assign_keypoints as assign_keypoints, constraint_score as constraint_score
from ._augment import (
    Augment as Augment,
    restore_keypoints as restore_keypoints,
    transform_images as transform_images,
)
from ._control import (
    FramePolicy as FramePolicy,
    image_target as image_target,
    swing_up as swing_up,
)
from ._controls import scene_actuators as scene_actuators
from ._data import (
    Frames as Frames,
    ImageSequences as ImageSequences,
    PlanarCamera as PlanarCamera,
    cache_directory as cache_directory,
)
from ._distil import distil_shifts as distil_shifts, shift_average as shift_average
from ._estimator import (
    AbstractKeypointEstimator as AbstractKeypointEstimator,
    KeypointEstimator as KeypointEstimator,
    KeypointEstimatorFC as KeypointEstimatorFC,
)
from ._evaluate import (
    draw_keypoints as draw_keypoints,
    encode_sequences as encode_sequences,
    keypoint_tracking as keypoint_tracking,
    pose_features as pose_features,
    predict as predict,
    predict_keypoints as predict_keypoints,
    prediction_threshold as prediction_threshold,
    valid_prediction_time as valid_prediction_time,
)
from ._files import (
    load_model as load_model,
    model_from_spec as model_from_spec,
    save_model as save_model,
)
from ._identify import ImageIdentification as ImageIdentification, identify as identify
from ._joints import (
    JointStructure as JointStructure,
    joint_structure as joint_structure,
    scene_joints as scene_joints,
)
from ._keypoints import (
    frame_to_pixel as frame_to_pixel,
    gaussian_maps as gaussian_maps,
    pixel_grid as pixel_grid,
    pixel_to_frame as pixel_to_frame,
    spatial_softmax as spatial_softmax,
)
from ._linearise import target_linearisation as target_linearisation
from ._loss import (
    ConstraintDrift as ConstraintDrift,
    HeatmapRegulariser as HeatmapRegulariser,
    KeypointDynamics as KeypointDynamics,
    Reconstruction as Reconstruction,
)
from ._model import KeyCLD as KeyCLD
from ._render import RenderProtocol as RenderProtocol, render as render, render_poses as render_poses
from ._renderer import (
    AbstractRenderer as AbstractRenderer,
    Renderer as Renderer,
    RendererFC as RendererFC,
)
from ._structure import scene_constraint as scene_constraint
from ._train import (
    Schedule as Schedule,
    TrainResult as TrainResult,
    train as train,
)

try:
    __version__ = importlib.metadata.version("cldyn")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"
