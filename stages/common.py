"""What every stage entry point shares: arguments, logging, error boundary, device."""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pipeline import cache
from pipeline.cache import CacheError
from pipeline.config import ConfigError
from pipeline.config_files import Loaded, load
from pipeline.device import choose_device

log = logging.getLogger("deep_ssfr")


class StageError(RuntimeError):
    """A stage cannot go on; the message says what failed and what to do."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that a terminated stage unwinds as Ctrl-C does."""


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated


@dataclass
class Run:
    """A stage invocation: the loaded config, the device and the flags."""

    loaded: Loaded
    device: str
    force: bool

    @property
    def config(self):
        return self.loaded.config

    @property
    def data_dir(self) -> Path:
        return self.loaded.data_dir


@dataclass(frozen=True)
class StageOptions:
    """What every stage command takes (``deep-ssfr <stage> --help``)."""

    config: str = "configs/default.yaml"
    scene: str = ""
    force: bool = False
    verify: bool = False
    executor: str = ""
    """'local' or 'ray' over the config's ``executor`` ('': the config's)."""


def train_scenes(run: Run) -> list[str]:
    """Scenes whose training split is used: ``train.train_scenes``, or every configured scene outside
    ``dataset.holdout_scenes`` (the refiner's and the metaball network's alike)."""
    cfg = run.config
    chosen = cfg.train.train_scenes or tuple(s for s in cfg.scenes if s not in cfg.dataset.holdout_scenes)
    for s in chosen:
        if s not in cfg.scenes:
            raise StageError(f"train.train_scenes names {s!r}, which is not in scenes {list(cfg.scenes)}")
    return [s for s in chosen if s in run.loaded.scenes]


def make_run(opts: StageOptions, overrides: dict | None = None) -> Run:
    """Load config (with ``overrides`` and the command line's executor) and choose the device."""
    overrides = {**(overrides or {}), **({"executor": opts.executor} if opts.executor else {})}
    loaded = load(opts.config, overrides=overrides, only_scene=opts.scene or None)
    cache.VERIFY_HASHES = opts.verify
    return Run(loaded, choose_device(loaded.config.device), opts.force)


def setup_logging() -> None:
    """One concise line per event on stderr."""
    if not logging.getLogger().handlers:
        logging.basicConfig(level=os.environ.get("DEEP_SSFR_LOG", "INFO"),
                            format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    for noisy in ("PIL", "matplotlib", "OpenGL", "trimesh"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def quiet_warp() -> None:
    """Keep Warp's banner and per-module load lines out of stage logs (Warp 1.19 reads
    ``config.log_level``; older releases ``config.quiet``)."""
    import warp as wp

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING


def _say(line: str) -> None:
    """Write one line to stderr in a single call, so a writer thread's log line cannot land inside it."""
    sys.stderr.write(line + "\n")
    sys.stderr.flush()


def stage_main(stage: str, body: Callable[[], None]) -> int:
    """Run a stage body, turning known failures into a one-line message and an exit code.

    Exit 2 for configuration errors (nothing written), 1 for input, cache or runtime failures;
    ``DEEP_SSFR_DEBUG=1`` re-raises instead, with the traceback.
    """
    setup_logging()
    quiet_warp()
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_terminated) if main else None
    try:
        body()
    except ConfigError as exc:
        _say(f"{stage}: config error: {exc}")
        return 2
    except (StageError, CacheError, ValueError, RuntimeError, FileNotFoundError) as exc:
        if os.environ.get("DEEP_SSFR_DEBUG"):
            raise
        _say(f"{stage}: error: {exc}")
        return 1
    except OSError as exc:
        # disk full, read-only file system, permissions: name the stage, the path and the cause
        if os.environ.get("DEEP_SSFR_DEBUG"):
            raise
        where = f" ({exc.filename})" if exc.filename else ""
        cause = exc.strerror or str(exc)
        _say(f"{stage}: error: {cause}{where}; finished outputs are kept: once that is fixed, the same command "
             "resumes")
        return 1
    except KeyboardInterrupt as exc:
        how, code = ("terminated", 143) if isinstance(exc, Terminated) else ("interrupted", 130)
        _say(f"{stage}: {how}; finished work is kept and the same command resumes")
        return code
    finally:
        cache.release_all()  # a stage that stopped half way still holds its entry's lock
        if main:
            signal.signal(signal.SIGTERM, previous)
    return 0
