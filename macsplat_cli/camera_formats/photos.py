"""The camera of each photo: cameras of ``--poses`` / ``--intrinsics`` (a cameras file or a COLMAP model) given to
the photos they are named after."""

from __future__ import annotations

import logging
import os
from collections import Counter
from collections.abc import Sequence
from pathlib import Path, PurePosixPath

from ..cameras import Camera, CameraSet
from ..errors import CameraFileError

logger = logging.getLogger(__name__)


def cameras_for_photos(cams: CameraSet, photos: Sequence[Path], where: str | os.PathLike[str]) -> list[Camera]:
    """The camera of each photo (``--poses``, ``--intrinsics``): the one named after it, by file name or stem
    (``a.jpg`` or ``a``), each camera to one photo (the same file given twice shares it). Only when no camera is
    named after any photo, and there are as many cameras as photos, are they taken in order, and the log says so.

    Args:
        where: the camera file, for messages.

    Raises:
        CameraFileError: some photos have a camera by name and others none; a photo has two (``a`` and ``a.jpg``);
            two photos claim one camera; or no name matches and the counts differ. The message names them.
    """
    by_name = {c.name: c for c in cams}
    # a COLMAP image name may hold its folder ("images/a.jpg"): its last part names the photo too, when unique
    last = Counter(PurePosixPath(c.name).name for c in cams)
    for c in cams:
        tail = PurePosixPath(c.name).name
        if tail != c.name and last[tail] == 1:
            by_name.setdefault(tail, c)
            by_name.setdefault(PurePosixPath(tail).stem, c)
    found = [list({id(m): m for n in (p.name, p.stem) if (m := by_name.get(n)) is not None}.values()) for p in photos]
    if not any(found):
        if len(cams) != len(photos):
            raise CameraFileError(
                f"{where}: no camera is named after a photo, and {len(cams)} cameras for {len(photos)} photos: "
                "give one camera per photo, named after it (file name or stem), or in the photos' order"
            )
        logger.info("%s: no camera is named after a photo: the %d cameras are taken in the photos' order (%s)",
                    where, len(cams), ", ".join(f"{p.name} → {c.name}" for p, c in zip(photos, cams)))  # fmt: skip
        return list(cams)
    missing = [p.name for p, f in zip(photos, found) if not f]
    if missing:
        raise CameraFileError(
            f"{where}: no camera named after {', '.join(repr(n) for n in missing)} (file name or stem), while other "
            "photos have theirs by name: name every photo's camera after it"
        )
    for p, f in zip(photos, found):
        if len(f) > 1:
            raise CameraFileError(f"{where}: photo {p.name!r} has two cameras, {f[0].name!r} and {f[1].name!r}")
    claims: dict[str, dict[str, str]] = {}  # camera name → {resolved photo path: photo name}
    for p, f in zip(photos, found):
        claims.setdefault(f[0].name, {})[os.path.realpath(p)] = str(p)
    for name, claimants in claims.items():
        if len(claimants) > 1:
            a, b = list(claimants.values())[:2]
            raise CameraFileError(f"{where}: photos {a!r} and {b!r} both claim camera {name!r}: one camera per photo")
    return [f[0] for f in found]
