"""Layer 4b, seeing the scene on the device: the learned estimator of the needle's and the tools' poses
from stereo endoscope frames (a keypoint network, its losses and training program, stereo triangulation
and the pose fit, its file, its errors)."""
