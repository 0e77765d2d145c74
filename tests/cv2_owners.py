"""The installed distributions that own files of the cv2 package; run as a script, prints them as JSON.

Standard library only, so that tests can run it in another environment's Python (tests/test_install.py).
"""

from __future__ import annotations

import importlib.metadata
import json


def cv2_owners() -> list[str]:
    """Names of the installed distributions with files in the cv2 package, sorted."""
    return sorted(
        {
            d.metadata["Name"]
            for d in importlib.metadata.distributions()
            if any(f.parts[0] == "cv2" for f in d.files or ())
        }
    )


if __name__ == "__main__":
    print(json.dumps(cv2_owners()))
