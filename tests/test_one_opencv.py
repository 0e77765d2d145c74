"""Exactly one OpenCV: the tests run against the OpenCV the service depends on, not one a test tool pulled in.

pycine requires opencv-python, whose cv2 overwrites opencv-contrib-python-headless's without a word from
pip; deploy/install.sh installs pycine without its dependencies.
"""

from __future__ import annotations

import importlib.metadata

import cv2

from tests.cv2_owners import cv2_owners

#: The OpenCV of the service's dependencies (pyproject.toml): every environment the project installs holds it alone.
SERVICE_OPENCV = "opencv-contrib-python-headless"


def test_exactly_one_distribution_owns_cv2() -> None:
    assert cv2_owners() == [SERVICE_OPENCV]


def test_the_cv2_imported_is_that_distributions() -> None:
    assert cv2.__version__ == ".".join(importlib.metadata.version(SERVICE_OPENCV).split(".")[:3])
    assert hasattr(cv2, "ximgproc")  # a contrib module: not opencv-python's cv2
