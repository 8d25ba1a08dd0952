"""OpenCV's predefined ArUco dictionaries this project prints markers and boards from, by name."""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator

# name -> how many marker ids it has
ARUCO_DICTIONARIES: dict[str, int] = {f"DICT_{bits}X{bits}_{n}": n for bits in (4, 5, 6, 7) for n in (50, 100, 250, 1000)}


def _known(name: str) -> str:
    if name not in ARUCO_DICTIONARIES:
        raise ValueError(f"unknown ArUco dictionary {name!r} (use one of DICT_4X4_50 ... DICT_7X7_1000)")
    return name


ArucoDictionary = Annotated[str, AfterValidator(_known)]  # a dictionary name OpenCV predefines
