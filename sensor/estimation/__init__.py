"""Estimation: RPC fitting to any model, Tikhonov regularisation (L-curve, GCV)."""
