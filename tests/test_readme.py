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
    command = ("bash scripts/setup.sh && .venv/bin/python -m ruff check rigsfm tests benchmarks workflows && "
               ".venv/bin/python -m mypy && .venv/bin/python -m pytest -q")
    assert f"```bash\n{command}\n```" in README
    assert command in (ROOT / ".ci" / "run").read_text().splitlines()


def test_bad_inputs_table_is_what_rigsfm_says():
    """README's "When something is wrong" table, row by row, against a fresh run of each case (the cases that
    need a mount namespace are only checked to be there). Refresh with `python tests/bad_inputs_table.py --readme`."""
    from bad_inputs_table import CASES, readme_rows, rows

    written = readme_rows(README)
    assert len(written) >= 30 and [row[0] for row in written] == [case.did for case in CASES]
    fresh = {row[0]: row for row in rows(isolated=False)}
    for row in written:
        if row[0] in fresh:
            assert row == fresh[row[0]], f"README row out of date:\n{row}\nrigsfm now says:\n{fresh[row[0]]}"
    assert len(fresh) == len(written) - sum(bool(case.isolated) for case in CASES)
