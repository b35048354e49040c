"""Where the EDS and the bundled scenes are, installed or in a source checkout.

The repository keeps one copy of each at its top: ``eds/taxel_node.eds`` (the one source of
the node's object dictionary) and ``scenes/`` (TOML scenes and their CSV taxel tables). A wheel
ships the same files inside the package, as ``taxel_net.eds`` and ``taxel_net.scenes``
(``pyproject.toml`` maps the two directories there). This module finds them either way, so
``fusion-center demo`` works after a plain ``pip install`` from any directory.

A scene can be named instead of given by path: ``matrix57`` is the bundled
``scenes/matrix57.toml`` (``fusion-center scenes`` lists them).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from .errors import SceneError

EDS_FILE = "taxel_node.eds"
_CHECKOUT = Path(__file__).resolve().parent.parent


def _data_dir(name: str) -> Path:
    """The installed ``taxel_net.<name>`` directory, else ``<checkout>/<name>``."""
    try:
        spec = importlib.util.find_spec(f"taxel_net.{name}")
    except ModuleNotFoundError:
        spec = None
    if spec is not None and spec.submodule_search_locations:
        return Path(list(spec.submodule_search_locations)[0])
    return _CHECKOUT / name


def eds_path() -> Path:
    """The taxel node's EDS (CiA 306), the one file twins and centre load their OD from."""
    return _data_dir("eds") / EDS_FILE


def scenes_dir() -> Path:
    """The directory of the bundled scenes."""
    return _data_dir("scenes")


def bundled_scenes() -> dict[str, Path]:
    """Name -> path of every bundled scene, sorted by name."""
    return {p.stem: p for p in sorted(scenes_dir().glob("*.toml"))}


def is_scene_name(text: str) -> bool:
    """True if ``text`` reads as a scene name (no directory part, no suffix), not a path."""
    return bool(text) and "/" not in text and "\\" not in text and not Path(text).suffix


def resolve_scene(text) -> Path:
    """A scene argument -> its file: an existing path as given, else a bundled scene's name.

    A name that is not bundled raises SceneError naming the bundled ones; a path is returned
    as given (the loader reports a missing file).
    """
    path = Path(text)
    if path.exists() or not is_scene_name(str(text)):
        return path
    scenes = bundled_scenes()
    if str(text) in scenes:
        return scenes[str(text)]
    raise SceneError(str(text), "scene", str(text),
                     f"no such file, nor a bundled scene (bundled: {', '.join(scenes) or 'none'})")
