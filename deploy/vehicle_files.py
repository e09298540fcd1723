"""The vehicle profiles shipped with slcp (``deploy/vehicles/*.toml``) and profile arguments."""

from __future__ import annotations

from pathlib import Path

from slcp.vehicles.profile import ProfileError, VehicleProfile, load_profile

#: the folder of the shipped vehicle profiles and agent files
SHIPPED = Path(__file__).resolve().parent / "vehicles"


def shipped_profiles() -> list[str]:
    """Names of the shipped profiles (their agent files, ``*.agent.toml``, left out)."""
    return sorted(p.stem for p in SHIPPED.glob("*.toml") if not p.name.endswith(".agent.toml"))


def profile_path(text: str | Path) -> Path:
    """A profile's file: ``text`` as a path, or the name of a shipped profile."""
    p = Path(text)
    if p.exists() or p.suffix == ".toml" or len(p.parts) > 1:
        return p
    shipped = SHIPPED / f"{text}.toml"
    if shipped.is_file():
        return shipped
    raise ProfileError(f"{text}: no such vehicle profile file, and not a shipped profile "
                       f"({', '.join(shipped_profiles())})")


def load_vehicle(text: str | Path) -> VehicleProfile:
    """The profile ``text`` names (:func:`profile_path`)."""
    return load_profile(profile_path(text))
