"""The stages' pictures, downscaled and embedded in the page as JPEG ``data:`` URIs (the page stays small)."""

from __future__ import annotations

import base64
import html
from pathlib import Path
from urllib.parse import quote

import cv2

from rigbuild.errors import InputError


def jpeg_bytes(path: Path, width: int, quality: int) -> bytes:
    """The image at ``path`` scaled to at most ``width`` px wide (aspect kept, never enlarged), as JPEG bytes."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("picture cannot be read", path=path, fix="re-run the rule that wrote it")
    h, w = img.shape[:2]
    if w > width:
        img = cv2.resize(img, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise InputError("picture cannot be encoded as JPEG", path=path)
    return buf.tobytes()


def figure(path: Path, caption: str, width: int, quality: int) -> str:
    """A ``<figure>`` with the downscaled picture, linked to the full-size file, and its caption: ``caption``
    is the file's path under the results folder, which holds the page, so the link is that path."""
    data = base64.b64encode(jpeg_bytes(path, width, quality)).decode("ascii")
    c = html.escape(caption)
    return (f'<figure><a href="{html.escape(quote(caption))}"><img alt="{c}" loading="lazy" '
            f'src="data:image/jpeg;base64,{data}"></a><figcaption>{c}</figcaption></figure>')
