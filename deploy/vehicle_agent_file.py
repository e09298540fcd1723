"""The agent file of an emulated vehicle as a deployed vehicle would carry it: no scenario, the
site from a Lanelet2 map, and the sensors' and the stop gap's models written out.

:func:`agent_config` (:mod:`deploy.agent_configs`) builds an agent's configuration from a
scenario; :func:`standalone_agent_toml` writes the same configuration as a file that needs no
scenario (``[agent] site`` and the ``[imu]``, ``[gnss]``, ``[uwb]`` and ``[stop_gap]`` sections).
Loaded with :func:`deploy.agent_config_file.load_agent_config`, it gives the same engine
configuration, to the map's precision (a test checks every field).
"""

from __future__ import annotations

import dataclasses
import json

from slcp.agent.methods import DEFAULT_FUSION, METHODS
from slcp.hw_emulation.scenario import Scenario


def _table(name: str, fields: dict[str, float | int | bool]) -> str:
    rows = "".join(f"{k} = {json.dumps(v)}\n" for k, v in fields.items())
    return f"[{name}]\n{rows}"


def standalone_agent_toml(scn: Scenario, vehicle: str, site: str, methods: tuple[str, ...] = METHODS,
                          fusion: str = DEFAULT_FUSION, lane_constraint: bool = True) -> str:
    """The ``[agent]``, ``[imu]``, ``[gnss]``, ``[uwb]`` and ``[stop_gap]`` sections of ``vehicle``
    of ``scn`` with its site from the Lanelet2 map ``site`` (a path as the file will name it)."""
    specs = {v.id: v for v in scn.vehicles}
    if vehicle not in specs:
        raise ValueError(f"vehicle {vehicle!r} not in scenario {scn.name!r}")
    sp = specs[vehicle]
    gm = sp.gnss
    agent = (f'[agent]\nvehicle = {json.dumps(vehicle)}\nsite = {json.dumps(site)}\n'
             f'methods = {json.dumps(list(methods))}\nfusion = {json.dumps(fusion)}\n'
             f'lane_constraint = {json.dumps(lane_constraint)}\n')
    # as agent_config has them: a scenario's agents weigh fixes against the multipath model,
    # with the χ² gate of FilterSettings (a site-less vehicle has neither)
    gnss = {"multipath_sigma": gm.multipath_h, "multipath_tau": gm.multipath_tau_moving,
            "multipath_tau_static": gm.multipath_tau_static, "white_sigma": max(gm.white_h, 0.1),
            "common_sigma": scn.common_mode_sigma, "common_tau": scn.common_mode_tau, "gate": 0.999}
    gap = {"m_xb": sp.stop_gap[0], "sigma_xb": sp.stop_gap[1], "m_yb": sp.lateral[0], "sigma_yb": sp.lateral[1],
           "l0": sp.l0}
    return "\n".join([agent, _table("imu", dataclasses.asdict(sp.imu)), _table("gnss", gnss),
                      _table("uwb", dataclasses.asdict(scn.uwb)), _table("stop_gap", gap)])
