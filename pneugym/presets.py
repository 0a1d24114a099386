"""Datasheet presets: standard single-rod cylinders (ISO 6432, bores 8-25 mm; ISO 15552, bores
32-320 mm) at any stroke, with a valve, tube and friction sized for them.

    from pneugym.presets import preset, cylinder_rig
    rig = preset("iso15552-50", stroke_mm=200, load_kg=10.0)     # a named preset
    rig = cylinder_rig(bore_mm=63, stroke_mm=500, supply_bar=6.0)  # any standard bore

Where each value comes from (``S`` a source of :data:`SOURCES`, ``E`` an estimate, stated):

- **Rod** (ISO 15552 / ISO 6432 dimension MM): the standards' tables [E: the stored text of
  ISO 15552 holds its front matter only; the 25 and 63 mm rods are confirmed by force
  arithmetic from Festo datasheets, S8, S9].
- **Port thread**: ISO 15552 bores 32-125 [S2, S3]; ISO 6432 [S4]; bores 160-320 [E].
- **Port area**: the passage of the port thread (M5 2.5 mm, G1/8 4 mm, G1/4 6 mm, G3/8 8 mm,
  G1/2 10 mm, G3/4 13 mm, G1 17 mm diameter) [E].
- **Cushion length**: bores 32-125 [S3], 25 mm [S8]; other bores [E, by the same trend];
  8 mm has elastic buffers only [S5]. Shortened to 0.45 x the stroke on short strokes. The
  drive-side cushion factor is the thesis rig's calibration; the exhaust needle is a tenth open
  (``cushion_factor_exhaust = 0.1``) [E: the thesis rig's 0.0101, a needle almost closed, makes
  the long cushions of the large bores take most of a short stroke: 2.2 s for 100 mm at
  125 mm bore, 0.40 s at 0.1].
- **Dead volume** per side: the cap face times ``4 mm + 0.04 x bore`` (the annulus on the rod
  side) [E: fitted to the estimated ranges of the research note, cushion bore and port channel:
  about 4 cm³ at 32 mm, 12 cm³ at 50 mm, 36 cm³ at 80 mm].
- **Moving mass** (piston and rod, without the payload): a steel rod of ``40 mm + 1.5 x bore``
  plus the stroke, and an aluminium piston ``0.2 x bore + 10 mm`` thick [E: gives 64.5 g for the
  25 mm cylinder at 0 mm stroke, the datasheet's 63.6 g, S8; 6.2 g per 10 mm against its 6 g].
- **Friction**: breakaway at 0.31 bar on the cap face for ISO 15552 (the thesis's measured
  Fs = 359 N on its 125 mm SMC C92 ISO cylinder, thesis 5.6) and 0.5 bar for ISO 6432 (the
  minimum operating pressure of SMC C85, 0.05 MPa, S4); Coulomb and viscous friction in the
  thesis's proportions (Table 5.1: C = 0.351 Fs; Kv per metre of seal circumference as the
  thesis rig's, 3965 N s/m²) [E beyond the thesis rig].
- **Valve**: the 5/3 valve class the catalogue's speed chart pairs with the bore [S6]: SY3000
  (C = 1.1 dm³/(s bar)) to 16 mm, SY5000 (2.8) to 32 mm, SY7000 (4.5) to 63 mm, SY9000 (10)
  to 160 mm; bores 200-320 [E: 20 and 40, ISO 5599 sizes 3-4]. Effective area S = 5.0 C mm²
  [S7]; the exhaust path the same. Switching delay 20 ms [E: solenoid valves of this class].
- **Tube**: 1 m, inner diameter by port (M5 2.5 mm, G1/8 4 mm, G1/4 5.5 mm, G3/8 7.5 mm, G1/2
  9 mm, G3/4 12 mm, G1 16 mm) [E: the usual push-in fitting per port].

These are a starting point for a rig file, not a measurement of your cylinder: fit what matters
with ``pneugym discrepancy`` on your measured runs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from .params import RigParams

#: Where the sourced values come from (see the module docstring).
SOURCES = {
    "S2": "Parker Origa, ISO cylinders: 'Bore 32, 40, 50, 63, 80, 100, 125; Ports 32 = 1/8, "
          "40/50 = 1/4, 63/80 = 3/8, 100/125 = 1/2'",
    "S3": "An ISO 15552 cylinder range 32-125 mm, specification table (maker not named): ports, "
          "cushioning length 24 (32, 40), 22 (50, 63), 32 (80, 100), 42 (125) mm",
    "S4": "SMC, ISO/VDMA cylinders, series C85 (ISO 6432): ports M5 (8-16 mm), G1/8 (20, 25 mm), "
          "operating pressure 0.05-1.0 MPa",
    "S5": "SMC, series C85 8-25 mm: air cushion only on bores 10 to 25 mm",
    "S6": "SMC, 5-port solenoid valve SY series (CAT.EUS11-83B-UK): sonic conductance C "
          "1.1 / 2.8 / 4.5 / 10 dm³/(s bar) for SY3000 / 5000 / 7000 / 9000, cylinder speed chart",
    "S7": "CKD, instruction manual SM-P00077-A (4G manifold valves): S = 5.0 C (S in mm²)",
    "S8": "Festo DSNU-S-25 datasheet (8148789): cushioning length 17 mm, moving mass 63.6 g at "
          "0 mm stroke plus 6 g per 10 mm, port G1/8, 0.6-10 bar",
    "S9": "Festo DGRF-C-63 datasheet: 1870 N / 1682 N at 6 bar (63 mm bore, 20 mm rod)",
    "thesis": "The thesis's rig: SMC C92 ISO cylinder, 125 mm bore, Fs = 359 N, C = 126 N, "
              "Kv = 1557 N s/m (5.6, Table 5.1)",
}


@dataclass(frozen=True)
class StandardBore:
    """One standard bore: the values the sizing rules start from (module docstring)."""

    standard: str
    bore_mm: float
    rod_mm: float
    port: str
    cushion_mm: float
    valve_c: float  # sonic conductance of the valve class [dm³/(s bar)]


#: port thread -> (port passage diameter [mm], tube inner diameter [mm]) [E]
PORTS = {"M5": (2.5, 2.5), "G1/8": (4.0, 4.0), "G1/4": (6.0, 5.5), "G3/8": (8.0, 7.5),
         "G1/2": (10.0, 9.0), "G3/4": (13.0, 12.0), "G1": (17.0, 16.0)}
_TABLE = (  # standard, bore, rod, port, cushion, valve C
    ("ISO 6432", 8, 4, "M5", 0.0, 1.1), ("ISO 6432", 10, 4, "M5", 8.0, 1.1),
    ("ISO 6432", 12, 6, "M5", 10.0, 1.1), ("ISO 6432", 16, 6, "M5", 13.0, 1.1),
    ("ISO 6432", 20, 8, "G1/8", 15.0, 2.8), ("ISO 6432", 25, 10, "G1/8", 17.0, 2.8),
    ("ISO 15552", 32, 12, "G1/8", 24.0, 2.8), ("ISO 15552", 40, 16, "G1/4", 24.0, 4.5),
    ("ISO 15552", 50, 20, "G1/4", 22.0, 4.5), ("ISO 15552", 63, 20, "G3/8", 22.0, 4.5),
    ("ISO 15552", 80, 25, "G3/8", 32.0, 10.0), ("ISO 15552", 100, 25, "G1/2", 32.0, 10.0),
    ("ISO 15552", 125, 32, "G1/2", 42.0, 10.0), ("ISO 15552", 160, 40, "G3/4", 55.0, 10.0),
    ("ISO 15552", 200, 40, "G3/4", 55.0, 20.0), ("ISO 15552", 250, 50, "G1", 65.0, 40.0),
    ("ISO 15552", 320, 63, "G1", 70.0, 40.0),
)
#: bore [mm] -> its standard values
BORES: dict[int, StandardBore] = {int(b): StandardBore(s, float(b), float(r), p, float(c), v)
                                  for s, b, r, p, c, v in _TABLE}
#: named presets -> bore [mm]
PRESETS = {"iso6432-12": 12, "iso6432-25": 25, "iso15552-32": 32, "iso15552-50": 50,
           "iso15552-80": 80, "iso15552-125": 125, "iso15552-200": 200}
STROKE_RANGE_MM = (10.0, 2000.0)  # the strokes the sizing rules are validated for
BREAKAWAY_BAR = {"ISO 15552": 359.0 / (math.pi / 4 * (0.125**2 - 0.032**2)) / 1e5,
                 "ISO 6432": 0.5}
COULOMB_PER_STATIC = 126.0 / 359.0  # thesis Table 5.1
VISCOUS_PER_CIRCUMFERENCE = 1557.0 / (math.pi * 0.125)  # [N s/m per m of seal]
STEEL, ALUMINIUM = 7850.0, 2700.0  # densities [kg/m³]
CD = 0.72  # the plant's discharge coefficient (ValveParams default)
CUSHION_EXHAUST = 0.1  # exhaust cushion needle, fraction of the exhaust path's area [E]


def _bore(bore_mm: float) -> StandardBore:
    if not isinstance(bore_mm, (int, float)) or isinstance(bore_mm, bool) \
            or float(bore_mm) not in BORES:
        raise ValueError(f"bore_mm = {bore_mm!r} is not a standard bore; standard bores [mm]: "
                         f"{sorted(BORES)} (ISO 6432: 8-25, ISO 15552: 32-320)")
    return BORES[int(bore_mm)]


def moving_mass_kg(bore_mm: float, stroke_mm: float) -> float:
    """Piston and rod [kg] of a standard cylinder (module docstring: an estimate)."""
    b = _bore(bore_mm)
    d, r, s = b.bore_mm * 1e-3, b.rod_mm * 1e-3, stroke_mm * 1e-3
    rod = STEEL * math.pi / 4 * r**2 * (0.04 + 1.5 * d + s)
    piston = ALUMINIUM * math.pi / 4 * (d**2 - r**2) * (0.2 * d + 0.01)
    return rod + piston


def cylinder_rig(bore_mm: float, stroke_mm: float, supply_bar: float = 6.0,
                 load_kg: float = 0.0, line_length_m: float = 1.0,
                 mounting_angle_deg: float = 0.0) -> RigParams:
    """A single-rod standard cylinder of ``bore_mm`` and ``stroke_mm`` [mm] with its valve and
    tube, at ``supply_bar`` (gauge), moving ``load_kg`` besides its own piston and rod."""
    b = _bore(bore_mm)
    lo, hi = STROKE_RANGE_MM
    ok = isinstance(stroke_mm, (int, float)) and not isinstance(stroke_mm, bool)
    if not (ok and lo <= stroke_mm <= hi):
        raise ValueError(f"stroke_mm = {stroke_mm!r} must be in [{lo:g}, {hi:g}] mm (the "
                         f"strokes the presets are validated for)")
    d, r, s = b.bore_mm * 1e-3, b.rod_mm * 1e-3, stroke_mm * 1e-3
    cap, ann = math.pi / 4 * d**2, math.pi / 4 * (d**2 - r**2)
    dead = 0.004 + 0.04 * d
    port_d, tube_d = PORTS[b.port]
    fs = BREAKAWAY_BAR[b.standard] * 1e5 * cap
    valve_area = 5.0 * b.valve_c * 1e-6 / CD
    return RigParams(supply_pressure_gauge_pa=supply_bar * 1e5, load_mass_kg=load_kg).with_(
        cylinder={"design": "single-rod", "bore_m": d, "rod_m": r, "stroke_m": s,
                  "dead_volume_m3": cap * dead, "dead_volume_rod_m3": ann * dead,
                  "port_area_m2": math.pi / 4 * (port_d * 1e-3) ** 2,
                  "cushion_length_m": min(b.cushion_mm * 1e-3, 0.45 * s),
                  "cushion_factor_exhaust": CUSHION_EXHAUST,
                  "moving_mass_extra_kg": moving_mass_kg(bore_mm, stroke_mm),
                  "mounting_angle_deg": mounting_angle_deg},
        line={"length_m": line_length_m, "diameter_m": tube_d * 1e-3},
        valve={"area_m2": valve_area, "exhaust_area_m2": valve_area, "delay_s": 0.02},
        friction={"static_n": fs, "coulomb_n": COULOMB_PER_STATIC * fs,
                  "viscous_n_s_per_m": VISCOUS_PER_CIRCUMFERENCE * math.pi * d})


def preset(name: str, stroke_mm: float = 200.0, **kwargs) -> RigParams:
    """The named preset of :data:`PRESETS` at ``stroke_mm``; keywords as :func:`cylinder_rig`."""
    if name not in PRESETS:
        from .params import did_you_mean

        raise ValueError(f"unknown preset {name!r}{did_you_mean(name, PRESETS)}; known: "
                         f"{sorted(PRESETS)}")
    return cylinder_rig(PRESETS[name], stroke_mm, **kwargs)
