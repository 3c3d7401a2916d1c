"""RPC00B files: readers for GeoTIFF/NITF tags (through GDAL), ``.RPB``, ``_RPC.TXT`` and DIMAP
v2 ``RPC_*.XML``, and writers for ``.RPB`` and GeoTIFF RPC tags.

:func:`read_rpc` detects the format from the file's content.
"""
from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from stereodem.sensor.errors import RPCError
from stereodem.sensor.models.rpc import (COEFF_KEYS, SCALAR_KEYS, RPCModel, _parse_coeffs,
                                         _parse_float, _RPB_KEYS)


def read_rpc(path) -> RPCModel:
    """Read an RPC model, detecting the format.

    Supported: GeoTIFF (or any GDAL raster) with RPC metadata (the TIFF RPC tag, or the
    ``<image>.RPB`` / ``<image>_RPC.TXT`` sidecars that GDAL picks up); a GDAL/DigitalGlobe
    ``.RPB`` file; a DigitalGlobe/GeoEye ``_RPC.TXT`` ("LINE_OFF: ..." key-value text); a
    Pleiades/SPOT 6-7 DIMAP v2 ``RPC_*.XML``. Image size comes from the raster (or its
    SOURCE_WIDTH/SOURCE_HEIGHT tags) or the DIMAP validity domain when available.
    """
    path = Path(path)
    if not path.is_file():
        raise RPCError(f"{path}: no such file")
    with open(path, "rb") as f:
        head = f.read(4096)
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return _read_raster(path)
    text_head = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if text_head.startswith(b"<"):
        return _read_dimap(path)
    if b"BEGIN_GROUP" in head or re.search(rb"lineOffset\s*=", head):
        return _read_rpb(path)
    if re.search(rb"LINE_OFF\s*:", head):
        return _read_rpc_txt(path)
    return _read_raster(path)


def _read_raster(path: Path) -> RPCModel:
    import rasterio
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(path) as ds:
                tags = ds.tags(ns="RPC")
                info = ds.tags()
                w, h = ds.width, ds.height
    except rasterio.errors.RasterioIOError as e:
        raise RPCError(f"{path}: not a readable raster or RPC file ({str(e).splitlines()[0][:80]})") from None
    if not tags:
        for side in (path.with_suffix(".RPB"), path.with_suffix(".rpb"),
                     path.with_name(path.stem + "_RPC.TXT"), path.with_name(path.stem + "_rpc.txt")):
            if side.is_file():
                m = read_rpc(side)
                m.width, m.height, m.source = w, h, str(side)
                return m
        raise RPCError(f"{path}: no RPC metadata (no RPC tags, .RPB or _RPC.TXT sidecar)")
    try:
        w = int(info.get("SOURCE_WIDTH", w))
        h = int(info.get("SOURCE_HEIGHT", h))
    except ValueError:
        raise RPCError(f"{path}: garbled SOURCE_WIDTH/SOURCE_HEIGHT tag") from None
    return RPCModel.from_dict(tags, path=str(path), width=w, height=h)


def _read_rpb(path: Path) -> RPCModel:
    text = path.read_text(errors="replace")
    d = {}
    for key, value in re.findall(r"(\w+)\s*=\s*([^;]*);", text, flags=re.S):
        if key in _RPB_KEYS:
            d[_RPB_KEYS[key]] = value.strip()
    return RPCModel.from_dict(d, path=str(path))


def _read_rpc_txt(path: Path) -> RPCModel:
    """DigitalGlobe/GeoEye ``_RPC.TXT``: one ``KEY: value [unit]`` per line, coefficients
    ``LINE_NUM_COEFF_1`` .. ``_20`` (or all 20 on one ``LINE_NUM_COEFF`` line)."""
    d = {}
    for line in path.read_text(errors="replace").splitlines():
        if ":" not in line:
            continue
        key, value = line.split(":", 1)
        key = key.strip().upper()
        fields = value.split()
        if not fields:
            d[key] = ""
        elif key in COEFF_KEYS:
            d[key] = value.strip()
        else:
            d[key] = fields[0]
    for key in COEFF_KEYS:
        if key not in d:
            items = []
            for i in range(1, 21):
                k = f"{key}_{i}"
                if k not in d:
                    raise RPCError(f"{path}: RPC key {k} missing")
                items.append(d[k])
            d[key] = items
    return RPCModel.from_dict(d, path=str(path))


def _read_dimap(path: Path) -> RPCModel:
    """Pleiades / SPOT 6-7 DIMAP v2 RPC file (``Global_RFM``)."""
    from xml.etree import ElementTree
    try:
        root = ElementTree.parse(path).getroot()
    except ElementTree.ParseError as e:
        raise RPCError(f"{path}: not well-formed XML ({e})") from None
    rfm = root.find(".//Global_RFM")
    if rfm is None:
        raise RPCError(f"{path}: no RPC metadata (no Global_RFM element of a DIMAP v2 RPC file)")

    def text(node, tag, where_):
        e = node.find(tag)
        if e is None or e.text is None or not e.text.strip():
            raise RPCError(f"{path}: RPC key {where_}/{tag} missing")
        return e.text.strip()

    inv = rfm.find("Inverse_Model")
    if inv is None:
        raise RPCError(f"{path}: RPC key Global_RFM/Inverse_Model missing")
    val = rfm.find("RFM_Validity")
    if val is None:
        raise RPCError(f"{path}: RPC key Global_RFM/RFM_Validity missing")
    d = {}
    for key in COEFF_KEYS:
        d[key] = [text(inv, f"{key}_{i}", "Inverse_Model") for i in range(1, 21)]
    for key in SCALAR_KEYS:
        d[key] = text(val, key, "RFM_Validity")
    # DIMAP counts pixels from 1 (centre of the first pixel at (1, 1)); we count from 0
    d["LINE_OFF"] = _parse_float(d["LINE_OFF"], "LINE_OFF", path) - 1.0
    d["SAMP_OFF"] = _parse_float(d["SAMP_OFF"], "SAMP_OFF", path) - 1.0
    loc = None
    direct = rfm.find("Direct_Model")
    if direct is not None:
        # Direct_Model: SAMP_* give longitude, LINE_* latitude (image -> ground)
        loc = np.stack([_parse_coeffs([text(direct, f"{key}_{i}", "Direct_Model") for i in range(1, 21)],
                                      f"Direct_Model/{key}", path)
                        for key in ("SAMP_NUM_COEFF", "SAMP_DEN_COEFF", "LINE_NUM_COEFF", "LINE_DEN_COEFF")])
    width = height = None
    dom = val.find("Direct_Model_Validity_Domain")
    if dom is not None:
        try:
            width = int(round(float(text(dom, "LAST_COL", "Direct_Model_Validity_Domain"))
                              - float(text(dom, "FIRST_COL", "Direct_Model_Validity_Domain")))) + 1
            height = int(round(float(text(dom, "LAST_ROW", "Direct_Model_Validity_Domain"))
                               - float(text(dom, "FIRST_ROW", "Direct_Model_Validity_Domain")))) + 1
        except (RPCError, ValueError):
            width = height = None
    return RPCModel.from_dict(d, path=str(path), width=width, height=height, loc_coeffs=loc)


# ---------------------------------------------------------------------- writers
def write_rpb(model, path, *, overwrite=False):
    """Write a GDAL/DigitalGlobe ``.RPB`` file (readable by GDAL as an image sidecar)."""
    from .raster import write_text_atomic
    f = lambda v: format(float(v), "+.17g")  # noqa: E731
    lines = ['satId = "UNKNOWN";', 'bandId = "P";', 'SpecId = "RPC00B";', "BEGIN_GROUP = IMAGE",
             f"\terrBias = {f(model.err_bias)};", f"\terrRand = {f(model.err_rand)};"]
    for key, attr in (("lineOffset", "line_off"), ("sampOffset", "samp_off"),
                      ("latOffset", "lat_off"), ("longOffset", "lon_off"),
                      ("heightOffset", "height_off"), ("lineScale", "line_scale"),
                      ("sampScale", "samp_scale"), ("latScale", "lat_scale"),
                      ("longScale", "lon_scale"), ("heightScale", "height_scale")):
        lines.append(f"\t{key} = {f(getattr(model, attr))};")
    for key, arr in (("lineNumCoef", model.line_num), ("lineDenCoef", model.line_den),
                     ("sampNumCoef", model.samp_num), ("sampDenCoef", model.samp_den)):
        body = ",\n".join(f"\t\t\t{f(v)}" for v in arr)
        lines.append(f"\t{key} = (\n{body});")
    lines += ["END_GROUP = IMAGE", "END;", ""]
    return write_text_atomic(path, "\n".join(lines), overwrite=overwrite)

def write_geotiff_rpc(model, path, *, data=None, overwrite=False):
    """Store the RPCs in a GeoTIFF's RPC metadata (TIFF RPC tag, GDAL RFC 22).

    With ``data`` (2-D or band-first 3-D array) a new GeoTIFF is written atomically
    (no overwrite unless ``overwrite``); without it the RPCs of the existing file ``path``
    are replaced in place.
    """
    import rasterio
    path = Path(path)
    if data is not None:
        from .raster import write_geotiff
        return write_geotiff(path, data, rpcs=model.to_rasterio(), overwrite=overwrite)
    if not path.is_file():
        raise RPCError(f"{path}: no such GeoTIFF to add RPC metadata to (pass data= to create one)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path, "r+") as ds:
            ds.rpcs = model.to_rasterio()
    return path
