"""Where :class:`PatchSyncBatch` was: it lives in :mod:`node_sim.patch.batch` (the patch node's
package, issue 22); re-exported here so that ``node_sim.patch_batch`` imports keep working."""

from __future__ import annotations

from .patch.batch import PatchSyncBatch, _BatchLayout  # noqa: F401 - re-exported

__all__ = ["PatchSyncBatch"]
