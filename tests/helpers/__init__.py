"""Helpers shared by the tests (issue #23: in one place): simulated scenes with RPCs
(:mod:`.rpc_scene`), orbital-model fixtures (:mod:`.orbital`). Statistics come from the
library itself (NMAD: :func:`stereodem.core.stats.nmad`). ``tests/`` is on ``sys.path``
(its ``conftest.py``), so tests import ``helpers.<module>``."""
