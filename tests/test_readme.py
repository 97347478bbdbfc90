"""The README's examples are valid input, and its commands are the ones CI runs."""

import re
from pathlib import Path

import yaml

from rigsfm.core.rig import parse_camera, parse_rigid3d

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def yaml_blocks():
    return [yaml.safe_load(block) for block in re.findall(r"```yaml\n(.*?)```", README, re.S)]


def test_rigs_yaml_example_is_valid():
    rigs_example = next(block for block in yaml_blocks() if "rigs" in block)
    for rig in rigs_example["rigs"]:
        for sensor in ("wide", "narrow"):
            parse_camera(rig["sensors"][sensor], f"README {sensor}")
        parse_rigid3d(rig["narrow_from_wide"], "README narrow_from_wide")


def test_ci_runs_the_readme_test_command():
    command = "bash scripts/setup.sh && .venv/bin/python -m pytest -q"
    assert f"```bash\n{command}\n```" in README
    assert command in (ROOT / ".ci" / "run").read_text().splitlines()
