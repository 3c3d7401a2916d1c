"""RPC models localised by the vendor's direct (image -> ground) polynomials, and the RPC
validity-range check.

Pleiades/SPOT DIMAP files (v1 ``F_LON``/``F_LAT``, v2 ``Direct_Model``, v3
``ImagetoGround_Values``), rpcm JSON (``lon_num`` ...) and "extended IKONOS" text files carry,
beside the ground -> image RPC00B polynomials, a second rational model for image -> ground.

**The default is the exact inverse** (:meth:`RPCModel.localize`: Newton iterations on the
projection, seeded by the direct model when present): localisation and projection are then
inverse to 1e-6 px, which space intersection, epipolar resampling and orthorectification rely
on. The vendor's direct model is a separate least-squares fit and departs from the inverse of
the projection by its fitting error (DIMAP states it as ``MODEL_PRECISION``, typically 1e-3
to 1e-2 px). :class:`DirectRPCModel` uses the direct model as the vendor intended (for
compatibility with software that does, e.g. OTB/OSSIM and shareloc; and about 5x faster);
``read_rpc(path, direct=True)`` and the CLI's ``--rpc-direct`` select it.
"""

from __future__ import annotations

import numpy as np

from stereodem.core.errors import RPCError, where
from stereodem.sensor.models.rpc import RPCModel, monomials

__all__ = ["DirectRPCModel", "check_validity"]


class DirectRPCModel(RPCModel):
    """An :class:`RPCModel` whose :meth:`localize` evaluates the direct polynomials.

    Built from an RPCModel carrying ``loc_coeffs`` (rows lon_num, lon_den, lat_num, lat_den of
    normalised (col, row, H) in the (L, P, H) slots, with the model's own normalisation).
    """

    MODEL_TYPE = "rpc_direct"

    @classmethod
    def from_rpc(cls, model: RPCModel) -> DirectRPCModel:
        if model.loc_coeffs is None:
            raise RPCError(
                f"{where(model.source)}the RPC file has no direct (image -> ground) model"
            )
        d = model.to_dict()
        return cls.from_dict(
            d,
            path=model.source,
            width=model.width,
            height=model.height,
            loc_coeffs=model.loc_coeffs,
        )

    def localize(self, col, row, h, **_ignored):
        """Image ``(col, row)`` at height ``h`` to ``(lon, lat)`` by the direct polynomials."""
        shape, cn, rn, H = self.normalised_image(col, row, h)
        with np.errstate(divide="ignore", invalid="ignore"):
            v = self.loc_coeffs @ monomials(cn, rn, H)
            lon = v[0] / v[1] * self.lon_scale + self.lon_off
            lat = v[2] / v[3] * self.lat_scale + self.lat_off
        return lon.reshape(shape), lat.reshape(shape)

    def to_dict(self) -> dict:
        d = super().to_dict()
        d.update(WIDTH=self.width, HEIGHT=self.height, LOC_COEFFS=self.loc_coeffs.tolist())
        return d

    @classmethod
    def from_dict(cls, d, *, path=None, width=None, height=None, loc_coeffs=None):
        d = dict(d)
        loc = d.pop("LOC_COEFFS", None) if loc_coeffs is None else loc_coeffs
        width = d.pop("WIDTH", None) if width is None else width
        height = d.pop("HEIGHT", None) if height is None else height
        if loc is None:
            raise RPCError(f"{where(path)}direct RPC model without LOC_COEFFS")
        return super().from_dict(d, path=path, width=width, height=height, loc_coeffs=loc)


def check_validity(model: RPCModel, lon, lat, h, *, tolerance: float = 0.1):
    """Raise :class:`RPCError` when ground points lie outside the RPC's validity range.

    The validity range is the normalisation box, ``|normalised coordinate| <= 1 + tolerance``
    in longitude, latitude and height (RPC00B polynomials are fitted inside it and diverge
    outside). Returns the boolean mask of valid points when all are inside.
    """
    lim = 1.0 + tolerance
    shape, nl, np_, nh = model.normalised_ground(lon, lat, h)
    bad = ((np.abs(nl) > lim) | (np.abs(np_) > lim) | (np.abs(nh) > lim)).reshape(shape)
    if bad.any():
        s = abs(model.height_scale)
        raise RPCError(
            f"{where(model.source)}{int(bad.sum())} of {bad.size} point(s) outside the "
            f"RPC validity range (lon {model.lon_off - abs(model.lon_scale):.4f}.."
            f"{model.lon_off + abs(model.lon_scale):.4f}, lat "
            f"{model.lat_off - abs(model.lat_scale):.4f}.."
            f"{model.lat_off + abs(model.lat_scale):.4f}, "
            f"h {model.height_off - s:.0f}..{model.height_off + s:.0f} m)"
        )
    return ~bad
