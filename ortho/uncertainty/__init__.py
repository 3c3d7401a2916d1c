"""Per-pixel uncertainty and sensitivity of orthoimages and DEMs (Bettemir 2006, 2010).

* :mod:`.propagation` — Jacobians of the ground position (E, N in a map CRS, metres) with
  respect to named model parameters, the DEM height and the imaging time; first-order
  propagation ``Σ = J D Jᵀ`` with a full covariance and grouped variance shares.
* :mod:`.sampling` — Monte Carlo with Latin hypercube samples and Iman–Conover rank
  correlation; regression measures SRC, PCC, PRCC.
* :mod:`.indices` — FAST and Sobol indices through SALib.
* :mod:`.maps` — orthoimage σ maps on the ortho grid and the DEM vertical σ.
* :mod:`.covariance` — the input covariance: ``--sigma`` pairs or an adjustment report.
"""
