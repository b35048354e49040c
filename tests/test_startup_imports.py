"""What a command's start-up imports: a module of the service package loads that module, not
the whole service (``fusion-center dcf`` needs master and lss; it imported the pipeline and with
it scipy.special and scipy.spatial, ~0.9 s of its 1.5 s CPU). One fresh interpreter, since this
test session has imported everything already. ``fusion-center fuse`` without a rate to compute
imports no scipy.special (its import is ~0.35 s of CPU; main imported it with the Poisson-binomial
module)."""

from __future__ import annotations

import subprocess
import sys

PROBE = """
import contextlib, io, sys
from fusion_center import cli
with contextlib.redirect_stdout(io.StringIO()) as fused:
    rc = cli.main(["fuse", "--rule", "additive", "--u", "1,1,-1,1", "--xi", "0.003", "--alpha", "0.03", "--json"])
print("fuse:", rc, '"decision"' in fused.getvalue(), "scipy.special" in sys.modules)
import fusion_center.service.master, fusion_center.service.lss
heavy = sorted(m for m in ("fusion_center.service.pipeline", "fusion_center.service.fusion_service",
                           "fusion_center.evaluation", "scipy.special", "scipy.spatial") if m in sys.modules)
print("heavy:", heavy)
import fusion_center.service as service
print("names:", service.FusionService.__module__, service.read_records.__module__, service.CyclePipeline.__name__,
      set(service.__all__) <= set(dir(service)), service.traces.__name__)
"""


def test_start_up_imports_only_what_the_command_needs():
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "fuse: 0 True False"
    assert lines[1] == "heavy: []"
    assert lines[2] == ("names: fusion_center.service.fusion_service fusion_center.service.records "
                        "CyclePipeline True fusion_center.service.traces")
