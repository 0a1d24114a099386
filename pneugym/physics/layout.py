"""Index layout of the packed arrays the kernels work on (the one place it is documented).

Parameters ``P`` (float64, length ``NP + n_cells``):
    fixed part indexed by the ``P_*`` constants below, then the ``n_cells`` line-cell volumes [m³]
    (tube volume plus any tee volume in the cell).

Continuous state ``y`` (float64, length ``2*n_cells - 1 + NY``), integrated by SSP-RK3:
    ``y[0:n]``          line-cell air masses [kg], cell 0 at the valve, cell n-1 at the port
    ``y[n:2n-1]``       mass flows at the interior faces [kg/s], positive towards the cylinder
                        (momentum states of the FD line; zero and unused by the lumped line)
    ``y[b + Y_*]``      with ``b = 2n - 1``: chamber masses [kg] and temperatures [K], piston
                        position [m] and velocity [m/s], lagged sensor pressures [Pa], cumulative
                        mass drawn from the supply and vented to atmosphere [kg].

Discrete state ``d`` (float64, length ``ND``): time, valve spool, friction/end-stop mode, counters
and the queue of pending valve commands, indexed by the ``D_*`` constants.
"""

# --- parameters -------------------------------------------------------------------------------
P_R = 0            # gas constant [J/(kg K)]
P_GAMMA = 1        # ratio of specific heats
P_T = 2            # ambient (= wall, supply, line) temperature [K]
P_PA = 3           # ambient pressure [Pa]
P_PS = 4           # supply pressure, absolute [Pa]
P_MU = 5           # dynamic viscosity [Pa s]
P_CDA_VALVE = 6    # Cd * A of the supply path through the main valve [m²]
P_CDA_PORT = 7     # Cd * A of the driving port [m²]
P_CDA_EXH = 8      # Cd * A of the exhaust path [m²]
P_CDA_LINE = 9     # Cd * A between lumped line volumes [m²] (lumped line only)
P_FLOW_MODEL = 10  # 0 = thesis eqs. 4.1-4.3, 1 = ISO 6358
P_ISO_B = 11       # ISO 6358 critical pressure ratio
P_LIN = 12         # relative pressure drop below which orifice flow is linear
P_DELAY = 13       # valve switching delay [s]
P_RAMP = 14        # valve opening/closing time [s]
P_AP = 15          # driving-side piston face area [m²] (the annulus of a double-rod cylinder)
P_STROKE = 16      # stroke [m]
P_V0D = 17         # driving-chamber volume at x = 0 [m³] (dead volume + extra dead volume)
P_V0E = 18         # exhaust-chamber volume at x = stroke [m³]
P_CUSH_LEN = 19    # cushion-zone length [m]
P_CUSH_FD = 20     # drive-port area factor inside the first zone
P_CUSH_FE = 21     # exhaust area factor inside the last zone
P_CUSH_RAMP = 22   # width of the smooth cushion transition [m]
P_MASS = 23        # moving mass [kg]
P_FS = 24          # static (breakaway) friction [N]
P_FC = 25          # Coulomb friction [N]
P_KV = 26          # viscous friction [N s/m]
P_STRIB_F = 27     # Stribeck extra force at v = 0 [N]
P_STRIB_V = 28     # Stribeck velocity [m/s]
P_CDA_LEAK_D = 29  # Cd * A of the leak drive -> atmosphere [m²]
P_CDA_LEAK_P = 30  # Cd * A of the leak across the piston [m²]
P_TAU_TH = 31      # thermal time constant of the chambers [s] (0 = isothermal)
P_LAG = 32         # pressure-sensor time constant [s] (0 = ideal)
P_LINE_MODEL = 33  # 0 = finite differences, 1 = lumped volumes, 2 = FD with implicit stages
P_NCELLS = 34      # number of line cells
P_DX = 35          # cell length [m]
P_LINE_A = 36      # tube cross-section [m²]
P_LINE_D = 37      # tube inner diameter [m]
P_DT = 38          # substep [s]
P_SQRT_T = 39      # sqrt(ambient temperature) [sqrt(K)]
P_OC = 40          # orifice constants block (pneugym.physics.orifice.NOC values)
P_AV = 47          # quadratic artificial-viscosity coefficient of the FD line (0 = none)
P_DIP_T0 = 48      # supply-pressure dip: start time [s]
P_DIP_DUR = 49     # supply-pressure dip: duration [s] (0 = no dip)
P_DIP_DEPTH = 50   # supply-pressure dip: depth, fraction of the gauge supply pressure
P_AE = 51          # exhaust-side piston face area [m²] (P_AP: the driving side's)
P_FLOAD = 52       # constant force along the motion [N]: gravity, external force (< 0 opposing)
P_KLAM_LEAK_D = 53  # laminar leak drive -> atmosphere, K = pi d^4 / (128 l) [m³] (0 = none)
NP = 54            # start of the cell volumes

# --- continuous state, offsets from b = 2 n - 1 -------------------------------------------------
Y_MD = 0    # driving-chamber air mass [kg]
Y_ME = 1    # exhaust-chamber air mass [kg]
Y_TD = 2    # driving-chamber temperature [K]
Y_TE = 3    # exhaust-chamber temperature [K]
Y_X = 4     # piston position from the retracted end [m]
Y_V = 5     # piston velocity [m/s]
Y_SD = 6    # lagged driving-port sensor pressure [Pa]
Y_SE = 7    # lagged exhaust-port sensor pressure [Pa]
Y_MIN = 8   # cumulative mass drawn from the supply [kg]
Y_MOUT = 9  # cumulative mass vented to atmosphere (exhaust and leaks) [kg]
NY = 10

# --- discrete state ---------------------------------------------------------------------------
D_T = 0          # time since the extend command [s]
D_S = 1          # main-valve opening [0, 1] at the start of the current spool ramp
D_T_S = 2        # start time of the current spool ramp [s]
D_TARGET = 3     # spool target of the current ramp (0 closed, 1 open)
D_T_EXH = 4      # time the exhaust path began to open [s] (1e30 = not yet)
D_MODE = 5       # 0 moving, 1 stuck (friction), 2 held at the extended end, 3 held at the retracted end
D_STICKS = 6     # number of moving -> stuck transitions away from the end stops
D_MOVED = 7      # 1 once the piston has broken away
D_T_ARRIVE = 8   # first time the piston reached the extended end [s] (-1 = not yet)
D_CMD = 9        # last command given (0/1)
D_T_CLOSED = 10  # time the valve last became fully closed after being open [s] (-1 = never)
D_STATUS = 11    # 0 ok, 1 non-finite state, 2 non-positive pressure/mass
D_NQ = 12        # number of queued valve commands
D_Q0 = 13        # queue: pairs (effective time [s], target), oldest first
QCAP = 64        # queue capacity (pairs): a change every 5 ms through a 0.3 s valve fits
ND = D_Q0 + 2 * QCAP
NEVER = 1e30

STATUS_OK = 0
STATUS_NONFINITE = 1
STATUS_NONPOSITIVE = 2

MODE_MOVING = 0
MODE_STUCK = 1
MODE_END = 2
MODE_START = 3

# --- recorded channels (Plant.run / kernel record) ---------------------------------------------
R_T = 0        # time [s]
R_X = 1        # position [m]
R_V = 2        # velocity [m/s]
R_PD = 3       # driving-chamber pressure [Pa]
R_PE = 4       # exhaust-chamber pressure [Pa]
R_PPORT = 5    # line pressure at the driving port (last cell) [Pa]
R_PVALVE = 6   # line pressure at the valve (first cell) [Pa]
R_S = 7        # main-valve opening [-]
R_SE = 8       # exhaust-path opening [-]
R_MIN = 9      # cumulative supply mass [kg]
R_TD = 10      # driving-chamber temperature [K]
R_TE = 11      # exhaust-chamber temperature [K]
R_SD = 12      # sensor pressure, driving port [Pa]
R_SE_P = 13    # sensor pressure, exhaust port [Pa]
R_CMD = 14     # valve command [-]
R_MDOT = 15    # supply mass flow [kg/s]
NR = 16
RECORD_NAMES = ("t", "x", "v", "p_drive", "p_exhaust", "p_port", "p_valve", "valve_opening",
                "exhaust_opening", "air_mass_in", "T_drive", "T_exhaust", "p_drive_sensor",
                "p_exhaust_sensor", "valve_cmd", "mdot_supply")
