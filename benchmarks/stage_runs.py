"""What the stage benchmarks share: a copy of a config pointed at a scratch cache, and a stage run
whose summary line is read back from its log."""

from __future__ import annotations

import io
import logging
import re
from pathlib import Path

import yaml

from stages import cli


def scratch_config(source: str | Path, data_dir: Path, **sections: dict) -> Path:
    """A copy of the config ``source`` whose cache is ``data_dir`` (its scenes still found beside
    ``source``) and whose ``sections`` (``simulate={...}``) are updated; written into ``data_dir``."""
    source = Path(source)
    body = yaml.safe_load(source.read_text())
    body.update(data_dir=str(data_dir), scene_dir=str(source.resolve().parent / body.get("scene_dir", "scenes")))
    for name, keys in sections.items():
        body.setdefault(name, {}).update(keys)
    Path(data_dir).mkdir(parents=True, exist_ok=True)
    config = Path(data_dir) / "config.yaml"
    config.write_text(yaml.safe_dump(body))
    return config


def logged_summary(stage: str, config: Path, scene: str, pattern: str, force: bool = False) -> re.Match:
    """Run ``deep-ssfr STAGE`` on ``scene`` (``force``: even if its output is cached) and match
    ``pattern`` in what it logged (its summary line); a run that logs none stops the benchmark,
    showing the log."""
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    logging.getLogger("deep_ssfr").addHandler(handler)
    try:
        assert cli.main([stage, "--config", str(config), "--scene", scene, *(["--force"] if force else [])]) == 0
    finally:
        logging.getLogger("deep_ssfr").removeHandler(handler)
    found = re.search(pattern, stream.getvalue())
    if found is None:
        raise SystemExit(f"the {stage} stage logged no summary:\n{stream.getvalue()}")
    return found
