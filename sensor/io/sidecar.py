"""Saving and loading sensor models (JSON sidecars) and finding an image's model.

A physical model is stored next to its image as ``<image stem>.model.json``:
``{"type": "<registered name>", "version": 1, ...}``. Every model class registers a
``to_dict()`` / ``from_dict()`` pair; :func:`load_image_model` prefers that sidecar (the exact
model) and falls back to the image's RPC metadata (GeoTIFF tags, ``.RPB``, ``_RPC.TXT``).
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

import numpy as np

from stereodem.core import jsonutil
from stereodem.core.errors import NoSensorModelError, RPCError, SensorModelError, not_found
from stereodem.core.raster import as_path, write_text_atomic
from stereodem.sensor.io.rpc_formats import read_rpc
from stereodem.sensor.models import frame
from stereodem.sensor.models.rpc import RPCModel

_REGISTRY: dict[str, tuple[type, callable, callable]] = {}


def register(name: str, cls: type, to_dict, from_dict):
    """Register a model class under ``name`` with its (de)serialisers."""
    _REGISTRY[name] = (cls, to_dict, from_dict)


def _jsonable(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    return v


def _ensure_registered():
    if "frame" not in _REGISTRY:
        names = [f.name for f in fields(frame.FrameCamera) if f.init]
        register(
            "frame",
            frame.FrameCamera,
            lambda m: {n: getattr(m, n) for n in names},
            lambda d: frame.FrameCamera(**{n: d[n] for n in names if n in d}),
        )
    if "rpcmodel" not in _REGISTRY:
        # the RPC00B metadata domain does not carry the image size: keep it in the sidecar

        register(
            "rpcmodel",
            RPCModel,
            lambda m: {**m.to_dict(), "width": m.width, "height": m.height},
            lambda d: RPCModel.from_dict(d, width=d.get("width"), height=d.get("height")),
        )
    for modname in (
        "pushbroom",
        "aster",
        "rpc",
        "rpc_direct",
        "corrected",
        "generic",
        "orbital.topan_los",
        "orbital.orun_natarajan",
        "orbital.kratky",
        "orbital.toutin",
    ):
        try:
            mod = __import__(f"stereodem.sensor.models.{modname}", fromlist=["_"])
        except ImportError:
            continue
        for cls in vars(mod).values():
            if (
                isinstance(cls, type)
                and hasattr(cls, "to_dict")
                and hasattr(cls, "from_dict")
                and getattr(cls, "__module__", "") == mod.__name__
            ):
                key = getattr(cls, "MODEL_TYPE", cls.__name__.lower())
                if key not in _REGISTRY:
                    register(key, cls, lambda m: m.to_dict(), cls.from_dict)


def model_to_dict(model) -> dict:
    _ensure_registered()
    for name, (cls, to_dict, _) in _REGISTRY.items():
        if type(model) is cls:
            return {"type": name, "version": 1, **_jsonable(to_dict(model))}
    raise SensorModelError(f"no serialiser for {type(model).__name__}")


def model_from_dict(d: dict, source=None):
    _ensure_registered()
    kind = d.get("type")
    if not isinstance(kind, str) or kind not in _REGISTRY:
        raise SensorModelError(f"{source or 'model'}: unknown model type {kind!r}")
    body = {k: v for k, v in d.items() if k not in ("type", "version")}
    try:
        return _REGISTRY[kind][2](body)
    except KeyError as exc:
        raise SensorModelError(
            f"{source or 'model'}: garbled {kind} model (missing key {exc})"
        ) from None
    except (TypeError, ValueError) as exc:
        raise SensorModelError(f"{source or 'model'}: garbled {kind} model ({exc})") from None


def save_model(model, path, *, overwrite=False):
    """Write a model to a JSON sidecar (atomically)."""
    return write_text_atomic(path, jsonutil.dumps(model_to_dict(model)), overwrite=overwrite)


def load_model(path, *, rpc_direct: bool = False):
    """Read a model from a JSON sidecar, or from an RPC file of any format
    :func:`stereodem.sensor.io.rpc_formats.read_rpc` reads (DIMAP ``RPC_*.XML``, ``.geom``,
    ``_RPC.TXT``, rpcm JSON, ...; ``rpc_direct`` as there)."""
    path = as_path(path, "sensor model")
    try:
        text = path.read_text(errors="replace")
    except FileNotFoundError:
        raise SensorModelError(not_found(path, "model file")) from None
    except (IsADirectoryError, PermissionError) as exc:
        raise SensorModelError(f"{path}: cannot read the model file ({exc.strerror})") from None
    try:
        d = json.loads(text)
    except json.JSONDecodeError:
        d = None
    if isinstance(d, dict) and "type" in d:
        return model_from_dict(d, source=path)

    try:
        return read_rpc(path, direct=rpc_direct)
    except RPCError as exc:
        why = str(exc).removeprefix(f"{path}: ")
        raise SensorModelError(
            f"{path}: neither a stereodem model file (JSON with a 'type') nor an RPC file ({why})"
        ) from None


def sidecar_path(image) -> Path:
    image = Path(image)
    return image.with_name(image.stem + ".model.json")


def load_image_model(image, *, prefer: str = "physical", rpc_direct: bool = False):
    """The sensor model of an image file.

    ``prefer="physical"`` uses the ``<stem>.model.json`` sidecar when present, else the RPC;
    ``prefer="rpc"`` uses the RPC only; ``rpc_direct`` localises an RPC with its file's
    direct model. Raises :class:`SensorModelError` naming the file when the image carries no
    usable model: :class:`NoSensorModelError` when it carries none at all (no sidecar, no
    RPCs), any other when the one it carries cannot be read (a garbled sidecar or RPCs).
    """
    image = Path(image)
    if not image.exists():
        raise SensorModelError(not_found(image, "image"))
    side = sidecar_path(image)
    if prefer == "physical" and side.exists():
        return load_model(side)
    try:
        return RPCModel.from_file(image, direct=rpc_direct)
    except RPCError as exc:
        if prefer == "rpc":  # the sidecar was not asked for: do not blame its absence
            raise SensorModelError(f"{image}: no usable RPC model ({exc})") from None
        none = isinstance(exc, NoSensorModelError)
        raise (NoSensorModelError if none else SensorModelError)(
            f"{image}: no usable sensor model (no {side.name} sidecar; {exc})"
        ) from None
