"""Scene calibration from the lab's own video (``meniscope calibrate``): analysis by synthesis through our renderer.

The unknowns of a scene file (fluid roughness and reflectance, the light, the camera's response and pose,
where the ROI sits in the recorded frame, the artifact spheres) are fitted jointly with the motion of a
handful of frames from several phases, on losses that see a highlight off by a few pixels (blurred
pyramids), coarse to fine, from several starts (:mod:`.fit`).
"""

#: Whole windows held to Eq. 1 by default (:mod:`.windows`): the ones whose frames move most among :data:`LOOKED`
#: spread over the recording (here, where ``meniscope --help`` reads them without loading the fit).
WINDOWS = 3
#: Windows read to choose them from.
LOOKED = 12
