"""Describe your own machine in a file, and see a bad file refused naming the field.

Run:  python examples/04_machine_file.py
"""

import tomllib
from pathlib import Path

from oga import MachineError, load_machine, stable_range
from oga.model.machine import machine_from_dict

preset = Path(__file__).parents[1] / "oga" / "presets" / "ucp710.toml"
data = tomllib.loads(preset.read_text())
data["name"] = "my-mill"
data["axes"]["x"]["cascade"]["mass_kg"] = 900.0  # a heavier table
machine = machine_from_dict(data)
rng = stable_range(machine, "x")
print(f"{machine.name}: X stable Kp range [{rng.kp_min}, {rng.kp_max}] (m/min)/mm")

data["axes"]["x"]["cascade"]["tn_s"] = -1.0
try:
    machine_from_dict(data, where="my-mill.toml")
except MachineError as err:
    print("refused:", err)
try:
    load_machine("nosuch")
except MachineError as err:
    print("refused:", err)
