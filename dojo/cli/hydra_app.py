"""Running a `dojo` subcommand as a Hydra application.

Hydra gives every configurable command `key=value` overrides, config groups, `--multirun` sweeps, `--cfg job`
and `--help`. Two things are added around it:
- the `suite` and `robot` groups are filled from the installed spec files, so every built-in suite or robot is a
  valid option without a second copy of it in the Hydra config;
- before Hydra runs, the overrides are composed once; an unknown key or a misspelled group option then fails
  with the closest valid name and exit code 2, instead of Hydra's traceback-like report.
"""

from __future__ import annotations

import os
import sys
from importlib import resources
from pathlib import Path
from typing import Callable

from omegaconf import DictConfig, OmegaConf

from dojo.compiler.spec_errors import did_you_mean
from dojo.compiler.spec_library import spec_files
from dojo.compiler.spec_yaml import read_spec_yaml

CONFIG_DIR = Path(str(resources.files("dojo.cli") / "config"))
_SPEC_GROUPS = {"suite": "suites", "robot": "robots"}  # config group -> folder of built-in specs


def _spec_ids(kind: str, packs: list[Path]) -> list[str]:
    """Ids of the built-in specs of one kind (their file names), plus those found in the given packs."""
    ids = [p.stem for p in (Path(str(resources.files("dojo.specs"))) / _SPEC_GROUPS[kind]).glob("*.yaml")]
    for pack in packs:
        for path in spec_files(pack) if pack.exists() else []:
            located, _ = read_spec_yaml(path, str(path))
            if located is not None and isinstance(located.data, dict) and located.data.get("kind") == kind:
                ids.append(path.stem)
    return sorted(set(ids))


def _packs_from(overrides: list[str]) -> list[Path]:
    """The `packs=[...]` override, read before Hydra runs so that the packs' suites are group options."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    for text in overrides:
        if text.startswith("packs="):
            value = OverridesParser.create().parse_override(text).value()
            return [Path(str(v)) for v in (value if isinstance(value, list) else [value])]
    return []


def _register_spec_groups(packs: list[Path]) -> None:
    """Make `suite=<id>` and `robot=<id>` choose among the spec files, built-in and in the given packs."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for kind in _SPEC_GROUPS:
        for spec_id in _spec_ids(kind, packs):
            store.store(group=kind, name=spec_id, node={"id": spec_id})


def group_options(group: str, packs: list[Path]) -> list[str]:
    """The options of a config group, from the config folder or the spec files."""
    if group in _SPEC_GROUPS:
        return _spec_ids(group, packs)
    return sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))


def _flat_keys(cfg: DictConfig, prefix: str = "") -> list[str]:
    keys = []
    for key in cfg.keys():
        full = f"{prefix}{key}"
        keys.append(full)
        node = cfg._get_node(key)  # no interpolation is resolved: `${now:...}` must not be evaluated here
        if isinstance(node, DictConfig):
            keys.extend(_flat_keys(node, full + "."))
    return keys


def check_overrides(config_name: str, overrides: list[str]) -> str | None:
    """Compose the config with `overrides` once; return a friendly message if that fails, else None."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException, OverrideParseException

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except OverrideParseException as err:
        return f"cannot read the overrides: {str(err).splitlines()[0]}"
    single = []
    for override in parsed:
        value = override.value()
        if override.is_sweep_override():
            value = next(iter(override.sweep_string_iterator()))
        elif not isinstance(value, str):
            value = override.get_value_element_as_str()
        single.append(f"{override.get_key_element()}={value}" if value is not None else override.input_line)

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            groups, keys = [], []
            for override, text in zip(parsed, single):
                key = override.key_or_group
                if override.is_add() or key.startswith("hydra") or override.package:
                    continue
                if key in _SPEC_GROUPS or (CONFIG_DIR / key).is_dir():
                    options = group_options(key, _packs_from(overrides))
                    for value in ([override.value()] if not override.is_sweep_override()
                                  else list(override.sweep_string_iterator())):
                        if str(value) not in options and value is not None:
                            return (f"unknown {key} '{value}'{did_you_mean(str(value), options)}; "
                                    f"options: {', '.join(options)}")
                    groups.append(text)
                else:
                    keys.append(key)
            # The chosen options' own keys are known keys (launcher=ray launcher.address=auto, backend=mjx
            # backend.impl=warp): they are read off the config composed with the group choices.
            known = _flat_keys(compose(config_name=config_name, overrides=groups))
            for key in keys:
                if key not in known:
                    hint = did_you_mean(key, known)  # a near miss is a typo: adding it as a new key would not help
                    return f"unknown key '{key}'" + (hint or f"; to add a new key write +{key}=VALUE")
            compose(config_name=config_name, overrides=single)
    except (HydraException, ValueError) as err:
        return str(err).splitlines()[0]
    finally:
        GlobalHydra.instance().clear()
    return None


_FLAGS_WITH_VALUES = {"--cfg", "-c", "--package", "-p", "--config-name", "-cn", "--config-dir", "-cd", "--info",
                      "--experimental-rerun"}


def overrides_of(argv: list[str]) -> list[str]:
    """The `key=value` overrides of a command line, without Hydra's flags and their values (`--cfg job`)."""
    values_of_flags = {i + 1 for i, a in enumerate(argv[:-1]) if a in _FLAGS_WITH_VALUES}
    return [a for i, a in enumerate(argv) if not a.startswith("-") and i not in values_of_flags]


def run_hydra_command(name: str, config_name: str, argv: list[str], task: Callable[[DictConfig], int]) -> int:
    """Run `task` under Hydra with `argv` (overrides and Hydra flags) and return its exit code."""
    import hydra

    from dojo.evaluation.run_dir import register_resolver

    register_resolver()
    overrides = overrides_of(argv)
    _register_spec_groups(_packs_from(overrides))
    if not {"--help", "-h", "--hydra-help"} & set(argv):
        problem = check_overrides(config_name, overrides)
        if problem:
            print(f"dojo {name}: {problem}", file=sys.stderr)
            return 2

    result: dict[str, int] = {}
    errors: list[BaseException] = []
    here = os.getpid()

    def _main(cfg: DictConfig) -> None:
        # Errors leave through our CLI's handler (one clear line), not Hydra's traceback printer. A sweep's job that
        # a launcher runs in another process (hydra/launcher=joblib or ray) cannot hand its error or exit code back
        # through these variables: there it raises, so that Hydra fails the job and the sweep, and `dojo` exits 1.
        try:
            code = task(cfg)
        except Exception as err:  # noqa: BLE001 - re-raised below, outside Hydra
            if os.getpid() != here:
                raise
            errors.append(err)
            return
        if code and os.getpid() != here:
            raise RuntimeError(f"dojo {name} ended with exit code {code}")
        result["code"] = max(result.get("code", 0), code)

    app = hydra.main(config_path=str(CONFIG_DIR), config_name=config_name, version_base="1.3")(_main)
    saved = sys.argv
    sys.argv = [f"dojo {name}"] + argv
    try:
        app()
    finally:
        sys.argv = saved
    if errors:
        raise errors[0]
    return result.get("code", 0)


def to_container(cfg: DictConfig) -> dict:
    """The resolved config as plain data (what the command implementations take)."""
    return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
