"""Live skeleton sources: a monocular camera (OpenCV + BlazePose on LiteRT) and a ZED stereo camera.

* :mod:`.model` installs and verifies the BlazePose weights (taken from a PyPI wheel at install
  time, never downloaded at run time): ``safemimic pose-model install``.
* :mod:`.blazepose` runs BlazePose's two stages (person detector → landmark model on a rotated
  region of interest, tracked from frame to frame) with numpy + OpenCV.
* :mod:`.geometry` turns image + metric landmarks into camera-frame 3D points (``cv2.solvePnP``),
  then into the 15 canonical keypoints in the robot frame (camera extrinsics).
* :mod:`.source` is the ``camera`` source, :mod:`.zed` the ``zed`` source (ZED SDK body tracking).

Nothing here is imported by the perception service unless one of these sources is configured.
"""
