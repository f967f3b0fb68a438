"""schemathesis over the whole OpenAPI of the running gateway, bounded (a fixed seed and
example count): no 5xx, no response off its schema, no schema-valid request refused
with a 4xx the API does not document for it."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

CONFIG = Path(__file__).with_name("schemathesis.toml")
EXAMPLES = 30
SEED = 2013


def schemathesis() -> list[str]:
    st = shutil.which("st", path=str(Path(sys.executable).parent))
    assert st, "schemathesis is a test dependency (pyproject [test])"
    return [st]


@pytest.mark.timeout(420)  # ~1100 cases: about 70 s on a quiet machine, longer under a loaded CI
def test_the_whole_api_under_schemathesis(campaign, tmp_path):
    url = f"http://127.0.0.1:{campaign.settings.gateway.http_port}"
    command = [*schemathesis(), "--no-color", "--config-file", str(CONFIG), "run", f"{url}/openapi.json",
               "--checks", "all", "--max-examples", str(EXAMPLES), "--seed", str(SEED),
               "--phases", "examples,coverage,fuzzing", "--request-timeout", "60", "--workers", "1",
               "--generation-database", "none", "--report", "junit", "--report-dir", str(tmp_path)]
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=400, cwd=tmp_path)  # its cache there
    finally:
        campaign.client.stop("schemathesis is done")  # it may have started a run
        campaign.client.http.post("/stage/resume")
    summary = result.stdout[-6000:]
    (Path(__file__).parents[2] / "test-artifacts").mkdir(exist_ok=True)
    (Path(__file__).parents[2] / "test-artifacts" / "schemathesis.txt").write_text(result.stdout + result.stderr)
    assert result.returncode == 0, summary + result.stderr[-2000:]
    cases = re.search(r"(\d+) generated", summary)
    assert cases and int(cases.group(1)) > 200, summary
