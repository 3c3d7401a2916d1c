"""RPC00B files: readers for every container the field uses, and writers for ``.RPB`` and
GeoTIFF RPC tags.

:func:`read_rpc` tries GDAL first (any raster GDAL opens: GeoTIFF/NITF RPC tags, a VRT with an
RPC metadata domain, and the ``.RPB`` / ``_RPC.TXT`` sidecars GDAL picks up), then sniffs the
file's content:

==========================  =========================================================  ===========
format                      recognised by                                              pixel (0,0)
==========================  =========================================================  ===========
DIMAP v2 (Pleiades, SPOT)   ``Global_RFM/Inverse_Model`` (``RPC_*.XML``)                 1-based
DIMAP v3 (Pleiades Neo)     ``Global_RFM/GroundtoImage_Values``                          0.5-based
DIMAP v1 (``PHRDIMAP*.XML``,  ``Global_RFM/Inverse_Model/F_COL`` + ``RFM_Validity/Col/A``   1-based
``MAP_*.XML``)
DigitalGlobe/Maxar XML      ``isd/RPB/IMAGE`` (WorldView-1/2/3, GeoEye, QuickBird)     0
OSSIM ``.geom``             ``line_num_coeff_00:`` keyword list (ossimRpcModel,          0
                            ossimPleiadesModel, ...)
``.RPB``                    ``BEGIN_GROUP = IMAGE`` / ``lineOffset =``                    0
``_RPC.TXT`` / IKONOS txt   ``LINE_OFF: <value> [unit]`` lines                            0
rpcm JSON                   ``{"row_offset": ...}`` (alone or under ``"rpc"``), or GDAL  0
                            RPC keys (``"LINE_OFF"``) in JSON
==========================  =========================================================  ===========

All are converted to stereodem's convention (centre of the first pixel at (0, 0)). Values may
carry units (``LINE_OFF: 149.5 pixels``), as GDAL's DigitalGlobe reader accepts. When no
reader accepts a file, the error names the formats tried.

Direct models (image -> ground polynomials of DIMAP, rpcm JSON and extended IKONOS files) are
kept as ``loc_coeffs``; by default they only seed the exact localisation,
``read_rpc(path, direct=True)`` returns a
:class:`stereodem.sensor.models.rpc_direct.DirectRPCModel` that localises with them (see that
module for why the exact inverse is the default).
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import rasterio

from stereodem.core.errors import NoSensorModelError, RPCError, not_found
from stereodem.core.raster import write_geotiff, write_text_atomic
from stereodem.sensor.models.rpc import (
    _RPB_KEYS,
    COEFF_KEYS,
    SCALAR_KEYS,
    RPCModel,
    _parse_coeffs,
    _parse_float,
)
from stereodem.sensor.models.rpc_direct import DirectRPCModel

#: formats named in the error when no reader accepts a file
FORMATS_TRIED = (
    "GDAL raster/VRT/NITF RPC metadata (with .RPB/_RPC.TXT sidecars)",
    "DIMAP v1/v2/v3 XML",
    "DigitalGlobe/Maxar XML",
    "OSSIM .geom keyword list",
    ".RPB",
    "_RPC.TXT/IKONOS text",
    "rpcm JSON",
)


def read_rpc(path, *, direct: bool = False) -> RPCModel:
    """Read an RPC model from any supported file (see the module docstring).

    Parameters
    ----------
    path : path-like
        Image or RPC file.
    direct : bool
        Localise with the file's direct (image -> ground) model
        (:class:`~stereodem.sensor.models.rpc_direct.DirectRPCModel`); an error when the file
        has none. Default: exact inverse of the projection.

    Returns
    -------
    RPCModel
        Image size from the raster (or its SOURCE_WIDTH/SOURCE_HEIGHT tags), the file's own
        size fields, or the RPC normalisation.
    """
    path = Path(path)
    if not path.is_file():
        raise RPCError(not_found(path, "RPC file"))
    model, gdal_note = _read_gdal(path)
    if model is None:
        model = _sniff(path)
    if model is None:
        why = f"; {gdal_note}" if gdal_note else ""
        raise NoSensorModelError(
            f"{path}: no RPC model found (tried: {', '.join(FORMATS_TRIED)}){why}"
        )
    if direct:
        return DirectRPCModel.from_rpc(model)
    return model


# ---------------------------------------------------------------------- GDAL
def _read_gdal(path: Path):
    """``(model, None)`` when GDAL opens the file and finds RPCs (tags or sidecars), else
    ``(None, note)``."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with rasterio.Env(CPL_LOG="/dev/null"), rasterio.open(path) as ds:
                tags = ds.tags(ns="RPC")
                info = ds.tags()
                w, h = ds.width, ds.height
    except Exception:  # rasterio raises several types for files GDAL cannot open
        return None, None
    if not tags:
        for side in (
            path.with_suffix(".RPB"),
            path.with_suffix(".rpb"),
            path.with_name(path.stem + "_RPC.TXT"),
            path.with_name(path.stem + "_rpc.txt"),
        ):
            if side.is_file() and side != path:
                m = read_rpc(side)
                m.width, m.height, m.source = w, h, str(side)
                return m, None
        return None, "GDAL opens it as a raster without RPC tags, .RPB or _RPC.TXT sidecar"
    try:
        w = int(info.get("SOURCE_WIDTH", w))
        h = int(info.get("SOURCE_HEIGHT", h))
    except ValueError:
        raise RPCError(f"{path}: garbled SOURCE_WIDTH/SOURCE_HEIGHT tag") from None
    return RPCModel.from_dict(tags, path=str(path), width=w, height=h), None


# ---------------------------------------------------------------------- sniffing
def _sniff(path: Path):
    with open(path, "rb") as f:
        head = f.read(8192)
    text_head = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if text_head.startswith(b"<"):
        return _read_xml(path)
    if text_head.startswith(b"{"):
        return _read_json(path)
    if b"BEGIN_GROUP" in head or re.search(rb"lineOffset\s*=", head):
        return _read_rpb(path)
    if re.search(rb"(?m)^\s*(?:\w+\.)?(?:line_num_coeff_00|line_off)\s*:", head):
        return _read_geom(path)
    if re.search(rb"LINE_OFF\s*:", head):
        return _read_rpc_txt(path)
    return None


def _read_rpb(path: Path) -> RPCModel:
    text = path.read_text(errors="replace")
    d = {}
    for key, value in re.findall(r"(\w+)\s*=\s*([^;]*);", text, flags=re.S):
        if key in _RPB_KEYS:
            d[_RPB_KEYS[key]] = value.strip()
    return RPCModel.from_dict(d, path=str(path))


def _coefficient_lists(d, path, prefixes=COEFF_KEYS):
    """Gather ``KEY_1`` .. ``KEY_20`` entries into ``KEY`` lists where ``KEY`` is absent."""
    for key in prefixes:
        if key not in d:
            items = []
            for i in range(1, 21):
                k = f"{key}_{i}"
                if k not in d:
                    raise RPCError(f"{path}: RPC key {k} missing")
                items.append(d[k])
            d[key] = items
    return d


def _read_rpc_txt(path: Path) -> RPCModel:
    """DigitalGlobe/GeoEye ``_RPC.TXT`` and IKONOS/Planet ``*_rpc.txt``: one ``KEY: value
    [unit]`` per line, coefficients ``LINE_NUM_COEFF_1`` .. ``_20`` (or all 20 on one
    ``LINE_NUM_COEFF`` line); "extended IKONOS" files add the direct model as
    ``LON_NUM_COEFF_1`` .. and ``LAT_*``."""
    d = {}
    for line in path.read_text(errors="replace").splitlines():
        if ":" not in line:
            continue
        key, value = line.split(":", 1)
        key = re.sub(r"[^A-Z0-9_]", "", key.strip().upper())
        fields = value.split()
        if not fields:
            d[key] = ""
        else:  # the whole value: a unit after it is checked by the number parser
            d[key] = value.strip()
    _coefficient_lists(d, path)
    loc = None
    if "LON_NUM_COEFF_1" in d or "LON_NUM_COEFF" in d:
        keys = ("LON_NUM_COEFF", "LON_DEN_COEFF", "LAT_NUM_COEFF", "LAT_DEN_COEFF")
        _coefficient_lists(d, path, keys)
        loc = np.stack([_parse_coeffs(d[k], k, path) for k in keys])
    return RPCModel.from_dict(d, path=str(path), loc_coeffs=loc)


def _read_geom(path: Path) -> RPCModel:
    """OSSIM keyword list (``.geom``): ``key:  value`` lines, coefficients
    ``line_num_coeff_00`` .. ``_19``; ``polynomial_format`` B (RPC00B) or absent."""
    kv = {}
    for line in path.read_text(errors="replace").splitlines():
        if ":" in line:
            key, value = line.split(":", 1)
            kv[key.strip()] = value.strip()

    def get(key):
        if key in kv:
            return kv[key]
        hits = [v for k, v in kv.items() if k.endswith("." + key)]
        if len(hits) == 1:
            return hits[0]
        raise RPCError(f"{path}: OSSIM keyword {key} missing")

    fmt = kv.get("polynomial_format", "B").strip().upper()
    if fmt != "B":
        raise RPCError(f"{path}: OSSIM polynomial_format {fmt!r} (only B, RPC00B, is supported)")
    d = {k: get(k.lower()) for k in SCALAR_KEYS}  # OSSIM: line_off ... height_scale
    for key in COEFF_KEYS:
        d[key] = [get(f"{key.lower()}_{i:02d}") for i in range(20)]
    for key, okey in (("ERR_BIAS", "bias_error"), ("ERR_RAND", "rand_error")):
        if okey in kv:
            d[key] = kv[okey]
    width = height = None
    try:
        if "number_samples" in kv and "number_lines" in kv:
            width, height = int(float(kv["number_samples"])), int(float(kv["number_lines"]))
        elif "image_size" in kv or "support_data.image_size" in kv:
            width, height = (
                int(float(v))
                for v in (kv.get("image_size") or kv["support_data.image_size"]).split()[:2]
            )
    except ValueError:
        raise RPCError(f"{path}: garbled OSSIM image size") from None
    return RPCModel.from_dict(d, path=str(path), width=width, height=height)


# ---------------------------------------------------------------------- JSON
_RPCM_SCALARS = {
    "LINE_OFF": "row_offset",
    "SAMP_OFF": "col_offset",
    "LAT_OFF": "lat_offset",
    "LONG_OFF": "lon_offset",
    "HEIGHT_OFF": "alt_offset",
    "LINE_SCALE": "row_scale",
    "SAMP_SCALE": "col_scale",
    "LAT_SCALE": "lat_scale",
    "LONG_SCALE": "lon_scale",
    "HEIGHT_SCALE": "alt_scale",
}
_RPCM_COEFFS = {
    "LINE_NUM_COEFF": "row_num",
    "LINE_DEN_COEFF": "row_den",
    "SAMP_NUM_COEFF": "col_num",
    "SAMP_DEN_COEFF": "col_den",
}


def _read_json(path: Path):
    """rpcm's JSON (``RPCModel.__dict__``: ``row_offset`` ..., alone or under ``"rpc"``, as in
    the IARPA/DFC JSON files), or GDAL RPC keys in a JSON object."""
    try:
        doc = json.loads(path.read_text(errors="replace"))
    except json.JSONDecodeError as e:
        raise RPCError(f"{path}: not valid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(doc, dict):
        return None
    width, height = doc.get("width"), doc.get("height")
    body = doc.get("rpc", doc) if isinstance(doc.get("rpc", doc), dict) else doc
    if "row_offset" in body:
        d = {}
        for key, jkey in {**_RPCM_SCALARS, **_RPCM_COEFFS}.items():
            if jkey not in body:
                raise RPCError(f"{path}: rpcm JSON key {jkey} missing")
            d[key] = body[jkey]
        loc = None
        if "lon_num" in body:
            loc = np.stack(
                [
                    _parse_coeffs(body[k], k, path)
                    for k in ("lon_num", "lon_den", "lat_num", "lat_den")
                ]
            )
        return RPCModel.from_dict(d, path=str(path), width=width, height=height, loc_coeffs=loc)
    if "LINE_OFF" in body:
        return RPCModel.from_dict(body, path=str(path), width=width, height=height)
    return None


# ---------------------------------------------------------------------- XML
def _read_xml(path: Path):
    try:
        root = ElementTree.parse(path).getroot()
    except ElementTree.ParseError as e:
        raise RPCError(f"{path}: not well-formed XML ({e})") from None
    if root.tag == "VRTDataset":
        raise RPCError(f"{path}: GDAL cannot open this VRT (missing or unreadable source?)")
    rfm = root.find(".//Global_RFM")
    if rfm is not None:
        if rfm.find("GroundtoImage_Values") is not None:
            return _read_dimap_v3(path, rfm)
        inv = rfm.find("Inverse_Model")
        if inv is not None and inv.find("F_COL") is not None:
            return _read_dimap_v1(path, root, rfm)
        return _read_dimap(path, rfm)
    if root.find("RPB/IMAGE") is not None or root.find(".//RPB/IMAGE") is not None:
        return _read_dg_xml(path, root)
    return None


def _text(node, tag, where_, path):
    e = node.find(tag)
    if e is None or e.text is None or not e.text.strip():
        raise RPCError(f"{path}: RPC key {where_}/{tag} missing")
    return e.text.strip()


def _validity_size(path, val):
    dom = val.find("Direct_Model_Validity_Domain") if val is not None else None
    if dom is None:
        return None, None
    try:
        t = lambda k: float(_text(dom, k, "Direct_Model_Validity_Domain", path))  # noqa: E731
        return (
            int(round(t("LAST_COL") - t("FIRST_COL"))) + 1,
            int(round(t("LAST_ROW") - t("FIRST_ROW"))) + 1,
        )
    except (RPCError, ValueError):
        return None, None


def _read_dimap(path: Path, rfm) -> RPCModel:
    """Pleiades / SPOT 6-7 DIMAP v2 RPC file (``Global_RFM``); DIMAP counts pixels from 1
    (centre of the first pixel at (1, 1)), we count from 0. ``Direct_Model``: ``SAMP_*`` give
    longitude, ``LINE_*`` latitude (image -> ground)."""
    return _dimap_rfm(
        path,
        rfm,
        "Inverse_Model",
        "Direct_Model",
        ("SAMP_NUM_COEFF", "SAMP_DEN_COEFF", "LINE_NUM_COEFF", "LINE_DEN_COEFF"),
        first_pixel=1.0,
    )


def _read_dimap_v3(path: Path, rfm) -> RPCModel:
    """Pleiades Neo DIMAP v3: ``GroundtoImage_Values`` / ``ImagetoGround_Values``, pixel
    offsets counted from the corner of the first pixel (centre at 0.5)."""
    return _dimap_rfm(
        path,
        rfm,
        "GroundtoImage_Values",
        "ImagetoGround_Values",
        ("LON_NUM_COEFF", "LON_DEN_COEFF", "LAT_NUM_COEFF", "LAT_DEN_COEFF"),
        first_pixel=0.5,
    )


def _dimap_rfm(
    path: Path, rfm, inverse_tag: str, direct_tag: str, direct_keys, *, first_pixel: float
) -> RPCModel:
    """An RPC model from a DIMAP v2/v3 ``Global_RFM`` element.

    Ground -> image coefficients ``{key}_1..20`` under ``inverse_tag``, normalisation under
    ``RFM_Validity``, the optional image -> ground model ``direct_keys`` (lon num/den, lat
    num/den) under ``direct_tag``; ``first_pixel`` is the file's coordinate of the centre of
    the first pixel (subtracted from ``LINE_OFF``/``SAMP_OFF``).
    """
    inv = rfm.find(inverse_tag)
    if inv is None:
        raise RPCError(f"{path}: RPC key Global_RFM/{inverse_tag} missing")
    val = rfm.find("RFM_Validity")
    if val is None:
        raise RPCError(f"{path}: RPC key Global_RFM/RFM_Validity missing")
    d = {
        key: [_text(inv, f"{key}_{i}", inverse_tag, path) for i in range(1, 21)]
        for key in COEFF_KEYS
    }
    for key in SCALAR_KEYS:
        d[key] = _text(val, key, "RFM_Validity", path)
    d["LINE_OFF"] = _parse_float(d["LINE_OFF"], "LINE_OFF", path) - first_pixel
    d["SAMP_OFF"] = _parse_float(d["SAMP_OFF"], "SAMP_OFF", path) - first_pixel
    loc = None
    direct = rfm.find(direct_tag)
    if direct is not None:
        loc = np.stack(
            [
                _parse_coeffs(
                    [_text(direct, f"{key}_{i}", direct_tag, path) for i in range(1, 21)],
                    f"{direct_tag}/{key}",
                    path,
                )
                for key in direct_keys
            ]
        )
    width, height = _validity_size(path, val)
    return RPCModel.from_dict(d, path=str(path), width=width, height=height, loc_coeffs=loc)


def _read_dimap_v1(path: Path, root, rfm) -> RPCModel:
    """Pleiades DIMAP v1 (``PHRDIMAP*.XML``, SPOT/Pleiades ``MAP_*.XML``): 40 values (20
    numerator, 20 denominator, RPC00B order) per ``F_COL``/``F_ROW`` (ground -> image) and
    ``F_LON``/``F_LAT`` (image -> ground); normalisation in ``RFM_Validity/<Lon|Lat|Alt|Col|Row>``
    as ``A`` (scale) and ``B`` (offset); pixels counted from 1."""
    inv = rfm.find("Inverse_Model")
    val = rfm.find("RFM_Validity")
    if val is None:
        raise RPCError(f"{path}: RPC key Global_RFM/RFM_Validity missing")

    def forty(node, tag, where_):
        items = _text(node, tag, where_, path).split()
        if len(items) != 40:
            raise RPCError(
                f"{path}: RPC key {where_}/{tag}: {len(items)} coefficient(s), expected 40"
            )
        return items[:20], items[20:]

    d = {}
    d["SAMP_NUM_COEFF"], d["SAMP_DEN_COEFF"] = forty(inv, "F_COL", "Inverse_Model")
    d["LINE_NUM_COEFF"], d["LINE_DEN_COEFF"] = forty(inv, "F_ROW", "Inverse_Model")
    for key, tag in (
        ("LONG", "Lon"),
        ("LAT", "Lat"),
        ("HEIGHT", "Alt"),
        ("SAMP", "Col"),
        ("LINE", "Row"),
    ):
        node = val.find(tag)
        if node is None:
            raise RPCError(f"{path}: RPC key RFM_Validity/{tag} missing")
        d[f"{key}_SCALE"] = _text(node, "A", f"RFM_Validity/{tag}", path)
        d[f"{key}_OFF"] = _text(node, "B", f"RFM_Validity/{tag}", path)
    d["LINE_OFF"] = _parse_float(d["LINE_OFF"], "LINE_OFF", path) - 1.0
    d["SAMP_OFF"] = _parse_float(d["SAMP_OFF"], "SAMP_OFF", path) - 1.0
    loc = None
    direct = rfm.find("Direct_Model")
    if direct is not None and direct.find("F_LON") is not None:
        ln, ld = forty(direct, "F_LON", "Direct_Model")
        an, ad = forty(direct, "F_LAT", "Direct_Model")
        loc = np.stack(
            [
                _parse_coeffs(c, f"Direct_Model/{k}", path)
                for k, c in (
                    ("F_LON[num]", ln),
                    ("F_LON[den]", ld),
                    ("F_LAT[num]", an),
                    ("F_LAT[den]", ad),
                )
            ]
        )
    width, height = _validity_size(path, val)
    if width is None:
        dims = root.find(".//Raster_Dimensions")
        if dims is not None and dims.find("NCOLS") is not None and dims.find("NROWS") is not None:
            try:
                width, height = int(dims.find("NCOLS").text), int(dims.find("NROWS").text)
            except (TypeError, ValueError):
                width = height = None
    return RPCModel.from_dict(d, path=str(path), width=width, height=height, loc_coeffs=loc)


def _read_dg_xml(path: Path, root) -> RPCModel:
    """DigitalGlobe/Maxar ``.XML`` (``isd``): ``RPB/IMAGE`` with ``LINEOFFSET`` ...,
    coefficient lists ``LINENUMCOEFList/LINENUMCOEF`` (20 values); size from
    ``IMD/NUMCOLUMNS``/``NUMROWS``."""
    im = root.find("RPB/IMAGE")
    if im is None:
        im = root.find(".//RPB/IMAGE")
    tags = {
        "LINE_OFF": "LINEOFFSET",
        "SAMP_OFF": "SAMPOFFSET",
        "LAT_OFF": "LATOFFSET",
        "LONG_OFF": "LONGOFFSET",
        "HEIGHT_OFF": "HEIGHTOFFSET",
        "LINE_SCALE": "LINESCALE",
        "SAMP_SCALE": "SAMPSCALE",
        "LAT_SCALE": "LATSCALE",
        "LONG_SCALE": "LONGSCALE",
        "HEIGHT_SCALE": "HEIGHTSCALE",
    }
    d = {k: _text(im, t, "RPB/IMAGE", path) for k, t in tags.items()}
    for key in COEFF_KEYS:
        tag = key.replace("_COEFF", "COEF").replace("_", "")
        lst = im.find(f"{tag}List")
        if lst is None:
            raise RPCError(f"{path}: RPC key RPB/IMAGE/{tag}List missing")
        d[key] = " ".join((e.text or "") for e in lst)
    for key, tag in (("ERR_BIAS", "ERRBIAS"), ("ERR_RAND", "ERRRAND")):
        e = im.find(tag)
        if e is not None and e.text and e.text.strip():
            d[key] = e.text.strip()
    width = height = None
    nc, nr = root.find("IMD/NUMCOLUMNS"), root.find("IMD/NUMROWS")
    if nc is not None and nr is not None:
        try:
            width, height = int(float(nc.text)), int(float(nr.text))
        except (TypeError, ValueError):
            width = height = None
    return RPCModel.from_dict(d, path=str(path), width=width, height=height)


# ---------------------------------------------------------------------- writers
def write_rpb(model, path, *, overwrite=False):
    """Write a GDAL/DigitalGlobe ``.RPB`` file (readable by GDAL as an image sidecar)."""
    f = lambda v: format(float(v), "+.17g")  # noqa: E731
    lines = [
        'satId = "UNKNOWN";',
        'bandId = "P";',
        'SpecId = "RPC00B";',
        "BEGIN_GROUP = IMAGE",
        f"\terrBias = {f(model.err_bias)};",
        f"\terrRand = {f(model.err_rand)};",
    ]
    for key, attr in (
        ("lineOffset", "line_off"),
        ("sampOffset", "samp_off"),
        ("latOffset", "lat_off"),
        ("longOffset", "lon_off"),
        ("heightOffset", "height_off"),
        ("lineScale", "line_scale"),
        ("sampScale", "samp_scale"),
        ("latScale", "lat_scale"),
        ("longScale", "lon_scale"),
        ("heightScale", "height_scale"),
    ):
        lines.append(f"\t{key} = {f(getattr(model, attr))};")
    for key, arr in (
        ("lineNumCoef", model.line_num),
        ("lineDenCoef", model.line_den),
        ("sampNumCoef", model.samp_num),
        ("sampDenCoef", model.samp_den),
    ):
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
    path = Path(path)
    if data is not None:
        return write_geotiff(path, data, rpcs=model.to_rasterio(), overwrite=overwrite)
    if not path.is_file():
        raise RPCError(f"{path}: no such GeoTIFF to add RPC metadata to (pass data= to create one)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path, "r+") as ds:
            ds.rpcs = model.to_rasterio()
    return path
