"""The scenario library: one YAML file per object of the paper's experiments."""
from pathlib import Path

SCENARIO_DIR = Path(__file__).resolve().parent


def list_scenarios() -> list[Path]:
    """All bundled scenario files, sorted by name."""
    return sorted(SCENARIO_DIR.glob("*.yaml"))


def find_scenario(name_or_path: str) -> Path:
    """A scenario by file path, or by the name of a bundled one (with or without `.yaml`)."""
    p = Path(name_or_path)
    if p.exists():
        return p
    cand = SCENARIO_DIR / (name_or_path if name_or_path.endswith(".yaml") else name_or_path + ".yaml")
    if cand.exists():
        return cand
    prefixed = [s for s in list_scenarios() if s.stem.startswith(name_or_path)]
    if len(prefixed) == 1:  # `exp01` for exp01-coffee-box
        return prefixed[0]
    from bagit.common.errors import BadScenario

    known = ", ".join(s.stem for s in list_scenarios()) or "none"
    raise BadScenario(f"no scenario file or bundled scenario named {name_or_path!r} (bundled: {known})")
