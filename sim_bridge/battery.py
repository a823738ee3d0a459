"""The robot's battery as the power board would report it (BATTERY_STATUS in a GCS).

A 3-cell LiPo pack: the open-circuit voltage follows the state of charge (a typical LiPo discharge
curve, piecewise linear between measured points), the terminal voltage sags by the pack's internal
resistance times the current, and the current is the electronics' idle draw plus what the two wheel
motors take for their speed (a ground robot's load is mostly its wheels). Charge is counted in sim
time. `status(counter)` is the BatteryStatus frame's signals (firmware_py/qnav.dbc), sent twice a
second.
"""

from __future__ import annotations

from dataclasses import dataclass

# (state of charge, volts per cell) of a LiPo cell discharged at a low rate
_OCV = ((0.0, 3.27), (0.05, 3.61), (0.1, 3.69), (0.2, 3.73), (0.5, 3.82), (0.8, 3.97), (0.9, 4.06), (1.0, 4.2))


@dataclass(frozen=True)
class BatteryParams:
    cells: int = 3
    capacity_mah: float = 5000.0
    internal_ohm: float = 0.06  # the whole pack
    idle_ma: float = 400.0  # computer, sensors, CAN
    motor_ma_per_mm_s: float = 3.0  # per wheel: 300 mm/s draws 0.9 A
    soc: float = 1.0  # at the start


def open_circuit_volts(soc: float, cells: int) -> float:
    soc = min(1.0, max(0.0, soc))
    for (s0, v0), (s1, v1) in zip(_OCV, _OCV[1:], strict=False):
        if soc <= s1:
            return cells * (v0 + (v1 - v0) * (soc - s0) / (s1 - s0))
    return cells * _OCV[-1][1]


class Battery:
    """State of charge and the last load; `step` per physics period."""

    def __init__(self, params: BatteryParams | None = None) -> None:
        self.params = params or BatteryParams()
        self.soc = self.params.soc
        self.current_ma = self.params.idle_ma

    def step(self, dt_s: float, left_mm_s: float, right_mm_s: float) -> None:
        p = self.params
        self.current_ma = p.idle_ma + p.motor_ma_per_mm_s * (abs(left_mm_s) + abs(right_mm_s))
        self.soc = max(0.0, self.soc - self.current_ma * dt_s / (p.capacity_mah * 3600.0))

    @property
    def volts(self) -> float:
        p = self.params
        return max(0.0, open_circuit_volts(self.soc, p.cells) - self.current_ma / 1000.0 * p.internal_ohm)

    def status(self, counter: int) -> dict[str, int]:
        return {"Bat_Voltage": round(self.volts * 1000), "Bat_Current": max(-32768, min(32767, round(self.current_ma))),
                "Bat_Remaining": round(self.soc * 100), "Bat_Counter": counter & 0xFF}
