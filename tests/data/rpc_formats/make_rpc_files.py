"""Write the real Pleiades RPC of ``../pleiades/img_01_rpc.tif`` in every RPC container
stereodem reads, by each format's published layout (see ``../SOURCES.md``).

The image -> ground ("direct") polynomials that DIMAP, rpcm JSON and extended IKONOS files
carry are fitted here to the exact localisation of the same RPC (unregularised RPC00B
rational fit on a 12 x 12 x 6 grid of the image and the height range).

Run from the repository: ``python tests/data/rpc_formats/make_rpc_files.py``.
"""

import json
import warnings
from pathlib import Path

import numpy as np
import rasterio
from rasterio.errors import NotGeoreferencedWarning

from stereodem.sensor.estimation.rpcfit import fit_rational
from stereodem.sensor.models.rpc import COEFF_KEYS, RPCModel

HERE = Path(__file__).resolve().parent
SRC = HERE.parent / "pleiades" / "img_01_rpc.tif"
f17 = lambda v: format(float(v), ".17g")  # noqa: E731


def direct_model(m):
    col, row, h = (
        a.ravel()
        for a in np.meshgrid(
            np.linspace(0, m.width - 1, 12),
            np.linspace(0, m.height - 1, 12),
            np.linspace(*m.height_bounds(), 6),
            indexing="ij",
        )
    )
    lon, lat = m.localize(col, row, h)
    cn, rn = (col - m.samp_off) / m.samp_scale, (row - m.line_off) / m.line_scale
    hn = (h - m.height_off) / m.height_scale
    lon_n, lon_d, _ = fit_rational(cn, rn, hn, (lon - m.lon_off) / m.lon_scale, regularization=0.0)
    lat_n, lat_d, _ = fit_rational(cn, rn, hn, (lat - m.lat_off) / m.lat_scale, regularization=0.0)
    return np.stack([lon_n, lon_d, lat_n, lat_d])


def coeffs(m):
    return dict(zip(COEFF_KEYS, (m.line_num, m.line_den, m.samp_num, m.samp_den)))


def dimap_v2(m, loc):
    c = coeffs(m)
    inv = "".join(
        f"<{k}_{i}>{f17(v)}</{k}_{i}>\n"
        for k in ("SAMP_NUM_COEFF", "SAMP_DEN_COEFF", "LINE_NUM_COEFF", "LINE_DEN_COEFF")
        for i, v in enumerate(c[k], 1)
    )
    direct = "".join(
        f"<{k}_{i}>{f17(v)}</{k}_{i}>\n"
        for k, row in zip(
            ("SAMP_NUM_COEFF", "SAMP_DEN_COEFF", "LINE_NUM_COEFF", "LINE_DEN_COEFF"), loc
        )
        for i, v in enumerate(row, 1)
    )
    val = (
        f"<LONG_SCALE>{f17(m.lon_scale)}</LONG_SCALE><LONG_OFF>{f17(m.lon_off)}</LONG_OFF>\n"
        f"<LAT_SCALE>{f17(m.lat_scale)}</LAT_SCALE><LAT_OFF>{f17(m.lat_off)}</LAT_OFF>\n"
        f"<HEIGHT_SCALE>{f17(m.height_scale)}</HEIGHT_SCALE><HEIGHT_OFF>{f17(m.height_off)}</HEIGHT_OFF>\n"
        f"<SAMP_SCALE>{f17(m.samp_scale)}</SAMP_SCALE><SAMP_OFF>{f17(m.samp_off + 1)}</SAMP_OFF>\n"
        f"<LINE_SCALE>{f17(m.line_scale)}</LINE_SCALE><LINE_OFF>{f17(m.line_off + 1)}</LINE_OFF>\n"
    )
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n<Dimap_Document name="RPC_PHR1A.XML">\n'
        '<Metadata_Identification><METADATA_FORMAT version="2.0">DIMAP</METADATA_FORMAT>'
        "<METADATA_PROFILE>PHR_SENSOR</METADATA_PROFILE></Metadata_Identification>\n"
        f"<Rational_Function_Model><Global_RFM>\n<Direct_Model>\n{direct}</Direct_Model>\n"
        f"<Inverse_Model>\n{inv}<ERR_BIAS_ROW>0</ERR_BIAS_ROW><ERR_BIAS_COL>0</ERR_BIAS_COL>\n"
        "</Inverse_Model>\n<RFM_Validity>\n<Direct_Model_Validity_Domain><FIRST_ROW>1</FIRST_ROW>"
        f"<FIRST_COL>1</FIRST_COL><LAST_ROW>{m.height}</LAST_ROW><LAST_COL>{m.width}</LAST_COL>"
        f"</Direct_Model_Validity_Domain>\n{val}</RFM_Validity>\n</Global_RFM></Rational_Function_Model>\n"
        "</Dimap_Document>\n"
    )


def dimap_v1(m, loc):
    c = coeffs(m)
    j = lambda *a: " ".join(f17(v) for v in np.concatenate(a))  # noqa: E731
    ab = lambda tag, s, o: f"<{tag}><A>{f17(s)}</A><B>{f17(o)}</B></{tag}>\n"  # noqa: E731
    return (
        '<?xml version="1.0" encoding="UTF-8" standalone="no"?>\n<PHR_Dimap_Document>\n'
        '<Metadata_Identification><METADATA_PROFILE version="1.4">PHR_SENSOR</METADATA_PROFILE>'
        "<METADATA_FORMAT>DIMAP_PHR</METADATA_FORMAT></Metadata_Identification>\n"
        "<Geoposition><Rational_Sensor_Model><Global_RFM>\n"
        f"<Direct_Model><F_LON>{j(loc[0], loc[1])}</F_LON>\n"
        f"<F_LAT>{j(loc[2], loc[3])}</F_LAT></Direct_Model>\n"
        f"<Inverse_Model><F_COL>{j(c['SAMP_NUM_COEFF'], c['SAMP_DEN_COEFF'])}</F_COL>\n"
        f"<F_ROW>{j(c['LINE_NUM_COEFF'], c['LINE_DEN_COEFF'])}</F_ROW></Inverse_Model>\n"
        "<RFM_Validity>\n"
        "<Direct_Model_Validity_Domain><FIRST_ROW>1</FIRST_ROW><FIRST_COL>1</FIRST_COL>"
        f"<LAST_ROW>{m.height}</LAST_ROW><LAST_COL>{m.width}</LAST_COL></Direct_Model_Validity_Domain>\n"
        + ab("Lon", m.lon_scale, m.lon_off)
        + ab("Lat", m.lat_scale, m.lat_off)
        + ab("Alt", m.height_scale, m.height_off)
        + ab("Col", m.samp_scale, m.samp_off + 1)
        + ab("Row", m.line_scale, m.line_off + 1)
        + "</RFM_Validity>\n</Global_RFM></Rational_Sensor_Model></Geoposition>\n"
        f"<Raster_Dimensions><NROWS>{m.height}</NROWS><NCOLS>{m.width}</NCOLS></Raster_Dimensions>\n"
        "</PHR_Dimap_Document>\n"
    )


def digitalglobe_xml(m):
    c = coeffs(m)
    lst = lambda tag, v: f"<{tag}List><{tag}>{' '.join(f17(x) for x in v)}</{tag}></{tag}List>\n"  # noqa: E731
    return (
        '<?xml version="1.0" encoding="UTF-8" standalone="yes"?>\n<isd>\n<IMD>'
        f"<NUMROWS>{m.height}</NUMROWS><NUMCOLUMNS>{m.width}</NUMCOLUMNS>"
        "<IMAGE><SATID>WV02</SATID></IMAGE></IMD>\n<RPB><SATID>WV02</SATID><BANDID>P</BANDID>"
        "<SPECID>RPC00B</SPECID>\n<IMAGE>\n<ERRBIAS>-1</ERRBIAS><ERRRAND>-1</ERRRAND>\n"
        f"<LINEOFFSET>{f17(m.line_off)}</LINEOFFSET><SAMPOFFSET>{f17(m.samp_off)}</SAMPOFFSET>\n"
        f"<LATOFFSET>{f17(m.lat_off)}</LATOFFSET><LONGOFFSET>{f17(m.lon_off)}</LONGOFFSET>\n"
        f"<HEIGHTOFFSET>{f17(m.height_off)}</HEIGHTOFFSET><LINESCALE>{f17(m.line_scale)}</LINESCALE>\n"
        f"<SAMPSCALE>{f17(m.samp_scale)}</SAMPSCALE><LATSCALE>{f17(m.lat_scale)}</LATSCALE>\n"
        f"<LONGSCALE>{f17(m.lon_scale)}</LONGSCALE><HEIGHTSCALE>{f17(m.height_scale)}</HEIGHTSCALE>\n"
        + lst("LINENUMCOEF", c["LINE_NUM_COEFF"])
        + lst("LINEDENCOEF", c["LINE_DEN_COEFF"])
        + lst("SAMPNUMCOEF", c["SAMP_NUM_COEFF"])
        + lst("SAMPDENCOEF", c["SAMP_DEN_COEFF"])
        + "</IMAGE>\n</RPB>\n</isd>\n"
    )


def ossim_geom(m):
    c = coeffs(m)
    lines = [
        "bias_error:  0",
        f"height_off:  {f17(m.height_off)}",
        f"height_scale:  {f17(m.height_scale)}",
        f"lat_off:  {f17(m.lat_off)}",
        f"lat_scale:  {f17(m.lat_scale)}",
    ]
    for key in ("LINE_DEN_COEFF", "LINE_NUM_COEFF"):
        lines += [f"{key.lower()}_{i:02d}:  {f17(v)}" for i, v in enumerate(c[key])]
    lines += [
        f"line_off:  {f17(m.line_off)}",
        f"line_scale:  {f17(m.line_scale)}",
        f"long_off:  {f17(m.lon_off)}",
        f"long_scale:  {f17(m.lon_scale)}",
        f"number_lines:  {m.height}",
        f"number_samples:  {m.width}",
        "polynomial_format:  B",
        "rand_error:  0",
    ]
    for key in ("SAMP_DEN_COEFF", "SAMP_NUM_COEFF"):
        lines += [f"{key.lower()}_{i:02d}:  {f17(v)}" for i, v in enumerate(c[key])]
    lines += [
        f"samp_off:  {f17(m.samp_off)}",
        f"samp_scale:  {f17(m.samp_scale)}",
        f"support_data.image_size:  {m.width} {m.height}",
        "type:  ossimRpcModel",
    ]
    return "\n".join(lines) + "\n"


def ikonos_txt(m, loc=None):
    """DigitalGlobe ``_RPC.TXT`` / IKONOS layout: values with units, 1-based coefficient names."""
    unit = {"LAT": "degrees", "LON": "degrees", "HEI": "meters"}
    lines = []
    for k, v in (
        ("LINE_OFF", m.line_off),
        ("SAMP_OFF", m.samp_off),
        ("LAT_OFF", m.lat_off),
        ("LONG_OFF", m.lon_off),
        ("HEIGHT_OFF", m.height_off),
        ("LINE_SCALE", m.line_scale),
        ("SAMP_SCALE", m.samp_scale),
        ("LAT_SCALE", m.lat_scale),
        ("LONG_SCALE", m.lon_scale),
        ("HEIGHT_SCALE", m.height_scale),
    ):
        lines.append(f"{k}: {float(v):+.17g} {unit.get(k[:3], 'pixels')}")
    for k, arr in coeffs(m).items():
        lines += [f"{k}_{i}: {float(v):+.17E}" for i, v in enumerate(arr, 1)]
    if loc is not None:
        for k, arr in zip(
            ("LON_NUM_COEFF", "LON_DEN_COEFF", "LAT_NUM_COEFF", "LAT_DEN_COEFF"), loc
        ):
            lines += [f"{k}_{i}: {float(v):+.17E}" for i, v in enumerate(arr, 1)]
    lines += ["ERR_BIAS: 0003.31 meters", "ERR_RAND: 0000.50 meters"]
    return "\n".join(lines) + "\n"


def rpcm_json(m, loc):
    c = coeffs(m)
    rpc = dict(
        row_offset=m.line_off,
        col_offset=m.samp_off,
        lat_offset=m.lat_off,
        lon_offset=m.lon_off,
        alt_offset=m.height_off,
        row_scale=m.line_scale,
        col_scale=m.samp_scale,
        lat_scale=m.lat_scale,
        lon_scale=m.lon_scale,
        alt_scale=m.height_scale,
        row_num=c["LINE_NUM_COEFF"].tolist(),
        row_den=c["LINE_DEN_COEFF"].tolist(),
        col_num=c["SAMP_NUM_COEFF"].tolist(),
        col_den=c["SAMP_DEN_COEFF"].tolist(),
        lon_num=loc[0].tolist(),
        lon_den=loc[1].tolist(),
        lat_num=loc[2].tolist(),
        lat_den=loc[3].tolist(),
    )
    return (
        json.dumps(
            {"img": "img_01.tif", "width": m.width, "height": m.height, "rpc": rpc}, indent=1
        )
        + "\n"
    )


def vrt(m):
    md = "".join(f'    <MDI key="{k}">{v}</MDI>\n' for k, v in m.to_dict().items())
    return (
        '<VRTDataset rasterXSize="8" rasterYSize="8">\n  <Metadata>\n'
        f'    <MDI key="SOURCE_WIDTH">{m.width}</MDI>\n'
        f'    <MDI key="SOURCE_HEIGHT">{m.height}</MDI>\n'
        '  </Metadata>\n  <Metadata domain="RPC">\n' + md + "  </Metadata>\n"
        '  <VRTRasterBand dataType="Byte" band="1">\n    <SimpleSource>\n'
        '      <SourceFilename relativeToVRT="1">../pleiades/img_01_rpc.tif</SourceFilename>\n'
        "      <SourceBand>1</SourceBand>\n    </SimpleSource>\n  </VRTRasterBand>\n</VRTDataset>\n"
    )


def main():
    m = RPCModel.from_file(SRC)
    loc = direct_model(m)
    (HERE / "RPC_PHR1A_P_pleiades-dimap2.XML").write_text(dimap_v2(m, loc))
    (HERE / "PHRDIMAP_pleiades-dimap1.XML").write_text(dimap_v1(m, loc))
    (HERE / "pleiades_worldview.XML").write_text(digitalglobe_xml(m))
    (HERE / "pleiades.geom").write_text(ossim_geom(m))
    (HERE / "pleiades_ikonos_rpc.txt").write_text(ikonos_txt(m, loc))
    (HERE / "pleiades_rpcm.json").write_text(rpcm_json(m, loc))
    (HERE / "pleiades_rpc.vrt").write_text(vrt(m))
    # an image whose RPCs come only from a DigitalGlobe _RPC.TXT sidecar (values with units)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(
            HERE / "dg_scene.tif", "w", driver="GTiff", width=8, height=8, count=1, dtype="uint8"
        ) as ds:
            ds.write(np.zeros((1, 8, 8), np.uint8))
            ds.update_tags(SOURCE_WIDTH=m.width, SOURCE_HEIGHT=m.height)
    (HERE / "dg_scene_RPC.TXT").write_text(ikonos_txt(m))


if __name__ == "__main__":
    main()
