"""A fake Universal Robots controller at the protocol level, for tests of the real ur-rtde client.

It serves the dashboard server (port 29999: a greeting, then one reply line per command line, as
UR's dashboard server documents them), the script port (30003: URScript sent as text; a script
that defines `rtde_control` runs as ur-rtde's control script, emulated by `ControlScript` on the
RTDE registers) and RTDE (Real-Time Data Exchange, protocol version 2, port 30004) as UR's RTDE
guide specifies it:
- every package is a header (uint16 size including the header, uint8 type) and a payload, big-endian;
- the client negotiates the protocol version ('V'), asks the controller version ('v'), sets up
  output recipes ('O': frequency and variable names; the reply gives a recipe id and the types,
  `NOT_FOUND` for an unknown name) and input recipes ('I': names; `IN_USE` or `NOT_FOUND` where
  they cannot be had), then starts ('S') or pauses ('P') synchronisation;
- once started, the controller sends a data package ('U') per output recipe at its frequency,
  and the client writes its inputs as data packages of an input recipe's id.

The controller's state is a sample per controller cycle (`ControllerState.publish`), stamped with
the cycle's own time: the arm's joints, its TCP from the controller's own kinematics (`UrKinematics`,
UR's published DH parameters, in the controller's base frame), and whatever the test sets. Every
RTDE client gets every sample at its recipe's rate. Inputs the client writes land in `inputs`, by
variable name. The arm is `JointArm` (speedJ integrated), or with `sim=` our own simulator
(`SimArm`: the world, the fingertip IMU and its board on a pseudo-terminal).
Each fake binds a loopback address of its own (127.0.0.x), because the ports are fixed.
"""
from __future__ import annotations

import collections
import math
import socket
import struct
import threading
import time

import numpy as np

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003
PROTOCOL_VERSION = 2

# package types
REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

# variable types and their struct formats
FORMATS = {"BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
           "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I"}


def _output_table() -> dict[str, str]:
    """The controller's output variables and their types (UR's RTDE guide, e-Series 5.x)."""
    t = {name: "VECTOR6D" for name in (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q", "actual_qd",
        "actual_current", "joint_control_output", "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force",
        "target_TCP_pose", "target_TCP_speed", "joint_temperatures", "actual_joint_voltage", "payload_inertia",
        "ft_raw_wrench", "actual_current_as_torque")}
    t.update({name: "DOUBLE" for name in (
        "timestamp", "actual_execution_time", "speed_scaling", "target_speed_fraction", "actual_momentum",
        "actual_main_voltage", "actual_robot_voltage", "actual_robot_current", "standard_analog_input0",
        "standard_analog_input1", "standard_analog_output0", "standard_analog_output1", "io_current",
        "tool_analog_input0", "tool_analog_input1", "tool_output_current", "tool_temperature", "tcp_force_scalar",
        "payload", "joint_position_deviation_ratio", "collision_detection_ratio")})
    t.update({name: "UINT32" for name in (
        "runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types", "tool_mode",
        "tool_analog_input_types", "output_bit_registers0_to_31", "output_bit_registers32_to_63",
        "input_bit_registers0_to_31", "input_bit_registers32_to_63", "script_control_line",
        "euromap67_input_bits", "euromap67_output_bits")})
    t.update({"robot_mode": "INT32", "safety_mode": "INT32", "safety_status": "INT32", "tool_output_voltage": "INT32",
              "time_scale_source": "INT32", "joint_mode": "VECTOR6INT32", "actual_tool_accelerometer": "VECTOR3D",
              "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D", "payload_cog": "VECTOR3D",
              "actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64"})
    for i in range(48):
        t[f"output_int_register_{i}"] = t[f"input_int_register_{i}"] = "INT32"
        t[f"output_double_register_{i}"] = t[f"input_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        t[f"output_bit_register_{i}"] = t[f"input_bit_register_{i}"] = "BOOL"
    return t


def _input_table() -> dict[str, str]:
    """The variables a client may write (UR's RTDE guide)."""
    t = {"speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE", "standard_digital_output_mask": "UINT8",
         "standard_digital_output": "UINT8", "configurable_digital_output_mask": "UINT8",
         "configurable_digital_output": "UINT8", "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
         "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
         "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
         "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
         "external_force_torque": "VECTOR6D"}
    for i in range(48):
        t[f"input_int_register_{i}"] = "INT32"
        t[f"input_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        t[f"input_bit_register_{i}"] = "BOOL"
    return t


OUTPUTS = _output_table()
INPUTS = _input_table()


def _zero(kind: str):
    fmt = FORMATS[kind]
    n = int(fmt[:-1]) if len(fmt) > 1 else 1
    value = False if kind == "BOOL" else (0.0 if fmt[-1] == "d" else 0)
    return [value] * n if n > 1 else value


class _Recipe:
    def __init__(self, names: list[str], kinds: list[str], frequency_hz: float = 0.0):
        self.names, self.kinds, self.frequency_hz = names, kinds, frequency_hz
        self.struct = struct.Struct(">" + "".join(FORMATS[k] for k in kinds))

    def pack(self, values: dict) -> bytes:
        flat = []
        for name, kind in zip(self.names, self.kinds):
            v = values.get(name)
            v = _zero(kind) if v is None else v
            flat.extend(v if isinstance(v, (list, tuple)) else [v])
        return self.struct.pack(*flat)

    def unpack(self, payload: bytes) -> dict:
        flat = list(self.struct.unpack(payload))
        out = {}
        for name, kind in zip(self.names, self.kinds):
            fmt = FORMATS[kind]
            n = int(fmt[:-1]) if len(fmt) > 1 else 1
            out[name] = flat[:n] if n > 1 else flat[0]
            del flat[:n]
        return out


def _read_exact(conn: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = conn.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("the client closed the connection")
        buf += chunk
    return buf


def _package(kind: int, payload: bytes = b"") -> bytes:
    return struct.pack(">HB", 3 + len(payload), kind) + payload


class _TcpServer:
    """A listening socket on (host, port) with a thread per connection: `_serve(conn)` is the
    protocol; the connection is closed and forgotten when it returns. `conn_timeout_s` is each
    connection's receive timeout (None: blocking)."""

    conn_timeout_s: float | None = None

    def _listen(self, host: str, port: int, name: str) -> None:
        self.stopped = threading.Event()
        self._sock = socket.create_server((host, port))
        self._sock.settimeout(0.1)
        self._conns: list[socket.socket] = []
        self._thread = threading.Thread(target=self._accept, name=f"{name}-{host}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self.stopped.set()
        for conn in list(self._conns):
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            conn.close()
        self._thread.join(2.0)
        self._sock.close()

    def _accept(self) -> None:
        while not self.stopped.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            conn.settimeout(self.conn_timeout_s)      # accepted sockets inherit the listening one's timeout
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conns.append(conn)
            threading.Thread(target=self._run, args=(conn,), name="fake-ur-conn", daemon=True).start()

    def _run(self, conn: socket.socket) -> None:
        try:
            self._serve(conn)
        except OSError:
            pass
        finally:
            try:
                conn.close()
            except OSError:
                pass
            if conn in self._conns:
                self._conns.remove(conn)

    def _serve(self, conn: socket.socket) -> None:
        raise NotImplementedError


class RtdeServer(_TcpServer):
    """RTDE on (host, 30004): the controller's samples (`ControllerState.samples_after`), each with
    its own timestamp. `version` is the controller's (major, minor, bugfix, build): major 5 is
    e-Series (500 Hz), 3 a CB3 (125 Hz); `max_frequency_hz` is its base rate."""

    def __init__(self, host: str, controller: "ControllerState", version=(5, 11, 0, 0), port: int = RTDE_PORT):
        self.host, self.port = host, port
        self.controller = controller
        self.version = version
        self.max_frequency_hz = controller_rate_hz(version)
        self.inputs: dict = {}                     # the latest value of every input variable written
        self._inputs_lock = threading.Lock()
        self.input_packages = 0
        self._listen(host, port, "rtde")

    def read_inputs(self) -> dict:
        with self._inputs_lock:
            return dict(self.inputs)

    def read_inputs_counted(self) -> tuple[dict, int]:
        """The inputs and how many input packages have come so far."""
        with self._inputs_lock:
            return dict(self.inputs), self.input_packages

    def _serve(self, conn: socket.socket) -> None:
        outputs: list[_Recipe] = []
        inputs: dict[int, _Recipe] = {}
        started = threading.Event()
        sender = None
        lock = threading.Lock()             # the sender thread and replies share the socket

        def send(data: bytes) -> None:
            with lock:
                conn.sendall(data)

        try:
            while not self.stopped.is_set():
                size, kind = struct.unpack(">HB", _read_exact(conn, 3))
                payload = _read_exact(conn, size - 3)
                if kind == REQUEST_PROTOCOL_VERSION:
                    (asked,) = struct.unpack(">H", payload)
                    send(_package(kind, struct.pack(">B", 1 if asked in (1, PROTOCOL_VERSION) else 0)))
                elif kind == GET_URCONTROL_VERSION:
                    send(_package(kind, struct.pack(">IIII", *self.version)))
                elif kind == SETUP_OUTPUTS:
                    (frequency,) = struct.unpack(">d", payload[:8])
                    names = [n for n in payload[8:].decode().split(",") if n]
                    kinds = [OUTPUTS.get(n, "NOT_FOUND") for n in names]
                    if "NOT_FOUND" in kinds or not 0 < frequency <= self.max_frequency_hz:
                        send(_package(kind, struct.pack(">B", 0) + ",".join(kinds).encode()))
                        continue
                    outputs.append(_Recipe(names, kinds, frequency))
                    send(_package(kind, struct.pack(">B", len(outputs)) + ",".join(kinds).encode()))
                elif kind == SETUP_INPUTS:
                    names = [n for n in payload.decode().split(",") if n]
                    kinds = [INPUTS.get(n, "NOT_FOUND") for n in names]
                    if "NOT_FOUND" in kinds:
                        send(_package(kind, struct.pack(">B", 0) + ",".join(kinds).encode()))
                        continue
                    recipe_id = len(inputs) + 1
                    inputs[recipe_id] = _Recipe(names, kinds)
                    send(_package(kind, struct.pack(">B", recipe_id) + ",".join(kinds).encode()))
                elif kind == START:
                    ok = bool(outputs)
                    send(_package(kind, struct.pack(">B", 1 if ok else 0)))
                    if ok and not started.is_set():
                        started.set()
                        sender = threading.Thread(target=self._send_data, args=(send, outputs, started),
                                                  name="rtde-data", daemon=True)
                        sender.start()
                elif kind == PAUSE:
                    started.clear()
                    send(_package(kind, struct.pack(">B", 1)))
                elif kind == DATA_PACKAGE:
                    recipe = inputs.get(payload[0])
                    if recipe is not None and len(payload) - 1 == recipe.struct.size:
                        values = recipe.unpack(payload[1:])
                        with self._inputs_lock:
                            self.inputs.update(values)
                            self.input_packages += 1
                # anything else: ignored, as the controller does with what it does not know
        except (ConnectionError, struct.error):
            pass
        finally:
            started.clear()

    def _send_data(self, send, outputs: list[_Recipe], started: threading.Event) -> None:
        """Every controller sample from now on, each output recipe at its own frequency (the
        controller's cycle divided down), as soon as the cycle that made it has published it."""
        seen = self.controller.count
        while started.is_set() and not self.stopped.is_set():
            for index, values in self.controller.samples_after(seen, 0.1):
                seen = index + 1
                wait = values["_due"] - time.monotonic()
                if wait > 0:
                    time.sleep(wait)           # a late sample: this one and every one after it
                try:
                    for recipe_id, recipe in enumerate(outputs, start=1):
                        every = max(1, int(round(self.max_frequency_hz / recipe.frequency_hz)))
                        if index % every == 0:
                            send(_package(DATA_PACKAGE, struct.pack(">B", recipe_id) + recipe.pack(values)))
                except OSError:
                    return


# -- the dashboard server ------------------------------------------------------------------------

ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT"}
NORMAL_MODE_BIT, PROTECTIVE_STOP_BIT = 0, 2          # safety_status_bits
POWER_ON_BIT, PROGRAM_RUNNING_BIT = 0, 1             # robot_status_bits


UNLOCK_AFTER_S = 5.0            # UR: a protective stop may be unlocked only this long after it occurred


class ControllerState:
    """The values both servers share (RTDE's output variables by name), under one lock."""

    def __init__(self, values: dict, model: str = "UR5", remote_control: bool = True,
                 version=(5, 11, 0, 0)):
        self.values = values
        self.model, self.remote_control, self.version = model, remote_control, version
        self.lock = threading.Condition()        # notified on every new sample
        self.loaded_program = "<unnamed>"
        self.serial_number = "20215500001"        # year, model code, number, as the controller reports it
        self.samples: collections.deque = collections.deque(maxlen=256)    # (index, values), oldest first
        self.count = 0                            # samples published so far
        # a protective stop: when it began (UR's dashboard unlocks it only 5 s after), and the pendant's popup
        self.protective_since: float | None = None
        self.popup = False

    def snapshot(self) -> dict:
        with self.lock:
            return dict(self.values)

    def publish(self, timestamp: float, delay_s: float = 0.0, **values) -> None:
        """One controller cycle's sample: the shared values with the arm's `values`, at `timestamp`
        (s on the controller's clock); `delay_s`: RTDE sends it this late (a congested link)."""
        with self.lock:
            self.values.update(values)
            self.samples.append((self.count, {**self.values, "timestamp": timestamp,
                                              "_due": time.monotonic() + delay_s}))
            self.count += 1
            self.lock.notify_all()

    def samples_after(self, seen: int, timeout: float) -> list[tuple[int, dict]]:
        """The samples from index `seen` on (those still kept), waiting up to `timeout` s for one."""
        with self.lock:
            self.lock.wait_for(lambda: self.count > seen, timeout)
            return [(i, v) for i, v in self.samples if i >= seen]

    def update(self, **values) -> None:
        with self.lock:
            if values.get("safety_mode") == 3 and self.values.get("safety_mode") != 3:
                self.protective_since, self.popup = time.monotonic(), True
            self.values.update(values)

    def program_running(self) -> bool:
        return bool(self.values.get("robot_status_bits", 0) >> PROGRAM_RUNNING_BIT & 1)

    def set_program_running(self, running: bool) -> None:
        with self.lock:
            bits = self.values.get("robot_status_bits", 0) & ~(1 << PROGRAM_RUNNING_BIT)
            self.values["robot_status_bits"] = bits | (int(running) << PROGRAM_RUNNING_BIT)
            self.values["runtime_state"] = 2 if running else 1          # PLAYING, STOPPED

    def unlock_protective_stop(self) -> bool:
        """False while not protective-stopped, or within UNLOCK_AFTER_S of the stop (UR's rule)."""
        with self.lock:
            if self.values.get("safety_mode") != 3:
                return False
            if self.protective_since is not None and time.monotonic() - self.protective_since < UNLOCK_AFTER_S:
                return False
            self.values["safety_mode"] = 1
            self.values["safety_status_bits"] = 1 << NORMAL_MODE_BIT
            return True


class DashboardServer(_TcpServer):
    """The dashboard server on (host, 29999): a greeting on connect, then a reply line per command."""

    GREETING = "Connected: Universal Robots Dashboard Server"

    def __init__(self, host: str, controller: ControllerState, port: int = DASHBOARD_PORT, on_stop=None):
        self.controller = controller
        self.on_stop = on_stop or (lambda: None)     # `stop`: the program stops
        self.commands: list[str] = []              # every command line received, in order
        self.not_understood: list[str] = []        # those the server answered "could not understand"
        self._listen(host, port, "dashboard")

    def _serve(self, conn: socket.socket) -> None:
        conn.sendall((self.GREETING + "\n").encode())
        buf = b""
        while not self.stopped.is_set():
            chunk = conn.recv(1024)
            if not chunk:
                return
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                command = line.decode(errors="replace").strip()
                self.commands.append(command)
                conn.sendall((self.reply(command) + "\n").encode())
                if command == "quit":
                    return

    def reply(self, command: str) -> str:
        c = self.controller
        v = c.snapshot()
        major, minor, bugfix, build = c.version
        lower = command.lower()
        if lower == "polyscopeversion":
            return f"URSoftware {major}.{minor}.{bugfix}.{build} (Jan 01 2022)"
        if lower == "is in remote control":
            return "true" if c.remote_control else "false"
        if lower == "robotmode":
            return f"Robotmode: {ROBOT_MODES.get(v.get('robot_mode'), 'NO_CONTROLLER')}"
        if lower == "safetymode":
            return f"Safetymode: {SAFETY_MODES.get(v.get('safety_mode'), 'FAULT')}"
        if lower == "safetystatus":
            return f"Safetystatus: {SAFETY_MODES.get(v.get('safety_mode'), 'FAULT')}"
        if lower == "programstate":
            return f"{'PLAYING' if c.program_running() else 'STOPPED'} {c.loaded_program}"
        if lower == "running":
            return f"Program running: {'true' if c.program_running() else 'false'}"
        if lower == "stop":
            if not c.program_running():
                return "Failed to execute: stop"
            self.on_stop()
            c.set_program_running(False)
            return "Stopped"
        if lower == "unlock protective stop":
            return "Protective stop releasing" if c.unlock_protective_stop() else \
                "Cannot unlock protective stop until 5s after occurrence. Always inspect cause of protective stop before unlocking"
        if lower == "close safety popup":
            c.popup = False
            return "closing safety popup"
        if lower == "close popup":
            return "closing popup"
        if lower == "get robot model":
            return c.model
        if lower == "get serial number":
            return c.serial_number
        if lower == "get loaded program":
            return "No program loaded" if c.loaded_program == "<unnamed>" else f"Loaded program: {c.loaded_program}"
        if lower == "power on":
            c.update(robot_mode=5)
            return "Powering on"
        if lower == "brake release":
            c.update(robot_mode=7)
            return "Brake releasing"
        if lower == "quit":
            return "Disconnected"
        self.not_understood.append(command)
        return f"could not understand: '{command}'"


# -- the controller's kinematics ----------------------------------------------------------------

# UR's published DH parameters (d1, a2, a3, d4, d5, d6), m, per arm; alpha is the same for all.
# The controller's base frame is the DH base: ur_description's `base`, not its `base_link`.
UR_DH = {
    "UR3": (0.1519, -0.24365, -0.21325, 0.11235, 0.08535, 0.0819),
    "UR5": (0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823),
    "UR10": (0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922),
    "UR3e": (0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921),
    "UR5e": (0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
    "UR10e": (0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
    "UR16e": (0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
}
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
E_SERIES_VERSION, CB3_VERSION = (5, 11, 0, 0), (3, 15, 7, 0)
CONTROLLER_UPTIME_S = 100.0         # the controller's clock had run this long when the fake started


def controller_rate_hz(version) -> float:
    return 500.0 if version[0] >= 5 else 125.0


def rotvec_to_matrix(rv) -> np.ndarray:
    rv = np.asarray(rv, float)
    angle = float(np.linalg.norm(rv))
    if angle < 1e-12:
        return np.eye(3)
    k = rv / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def matrix_to_rotvec(R) -> np.ndarray:
    """A rotation vector of angle [0, pi] (as the controller reports it), through the quaternion
    (Shepperd's method: well conditioned near a half turn, where tool-down poses live)."""
    t = np.trace(R)
    i = int(np.argmax([t, R[0, 0], R[1, 1], R[2, 2]]))
    if i == 0:
        w = math.sqrt(1 + t) / 2
        x, y, z = (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)
    elif i == 1:
        x = math.sqrt(1 + 2 * R[0, 0] - t) / 2
        w, y, z = (R[2, 1] - R[1, 2]) / (4 * x), (R[0, 1] + R[1, 0]) / (4 * x), (R[0, 2] + R[2, 0]) / (4 * x)
    elif i == 2:
        y = math.sqrt(1 + 2 * R[1, 1] - t) / 2
        w, x, z = (R[0, 2] - R[2, 0]) / (4 * y), (R[0, 1] + R[1, 0]) / (4 * y), (R[1, 2] + R[2, 1]) / (4 * y)
    else:
        z = math.sqrt(1 + 2 * R[2, 2] - t) / 2
        w, x, y = (R[1, 0] - R[0, 1]) / (4 * z), (R[0, 2] + R[2, 0]) / (4 * z), (R[1, 2] + R[2, 1]) / (4 * z)
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    v = np.array([x, y, z])
    s = float(np.linalg.norm(v))
    return np.zeros(3) if s < 1e-15 else v / s * 2 * math.atan2(s, w)


class UrKinematics:
    """The controller's forward kinematics: UR's DH parameters and its TCP setting (x, y, z, rotation
    vector, flange frame); poses and speeds in its base frame, as RTDE reports them."""

    def __init__(self, arm: str, tcp_offset=(0.0,) * 6):
        d1, a2, a3, d4, d5, d6 = UR_DH[arm]
        self.d, self.a = (d1, 0.0, 0.0, d4, d5, d6), (0.0, a2, a3, 0.0, 0.0, 0.0)
        self.flange_tcp = np.eye(4)
        self.flange_tcp[:3, :3] = rotvec_to_matrix(tcp_offset[3:])
        self.flange_tcp[:3, 3] = tcp_offset[:3]

    def _joint(self, qi: float, d: float, a: float, alpha: float) -> np.ndarray:
        ct, st, ca, sa = math.cos(qi), math.sin(qi), math.cos(alpha), math.sin(alpha)
        return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
                         [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]])

    def matrix(self, q) -> np.ndarray:
        T = np.eye(4)
        for qi, d, a, alpha in zip(q, self.d, self.a, DH_ALPHA):
            T = T @ self._joint(qi, d, a, alpha)
        return T @ self.flange_tcp

    def pose(self, q) -> list:
        T = self.matrix(q)
        return list(T[:3, 3]) + list(matrix_to_rotvec(T[:3, :3]))

    def speed(self, q, qd) -> list:
        return self.pose_speed(q, qd)[1]

    def pose_speed(self, q, qd) -> tuple[list, list]:
        """The TCP's pose and its linear and angular velocity, base frame, from one pass along the chain:
        each joint turns about its z axis (the DH frame before it), so v = sum z_i x (p_tcp - p_i) qd_i and
        w = sum z_i qd_i (the geometric Jacobian: the controller's cycle cannot spare finite differences)."""
        T = np.eye(4)
        axes, origins = np.empty((6, 3)), np.empty((6, 3))
        for i, (qi, d, a, alpha) in enumerate(zip(q, self.d, self.a, DH_ALPHA)):
            axes[i], origins[i] = T[:3, 2], T[:3, 3]
            T = T @ self._joint(qi, d, a, alpha)
        T = T @ self.flange_tcp
        rate = np.asarray(qd, dtype=float)
        r = T[:3, 3] - origins
        v = ((axes[:, [1, 2, 0]] * r[:, [2, 0, 1]] - axes[:, [2, 0, 1]] * r[:, [1, 2, 0]]).T @ rate)  # z_i x r_i
        return list(T[:3, 3]) + list(matrix_to_rotvec(T[:3, :3])), list(v) + list(axes.T @ rate)


# -- the simulated arm -----------------------------------------------------------------------

class SimArmSpec:
    """What the fake needs to run our simulator as its arm (picklable): sim.process.SimSpec with
    imu_out "wire" and the board's pty path. The simulator's commands come from speedJ, ramped at
    its acceleration every controller cycle, and its states are the controller's samples."""

    def __init__(self, sim_spec):
        self.sim_spec = sim_spec


class SimArm:
    """The fake's arm as our simulator (sim.robot.SimRobot on its URDF, its world, the fingertip
    IMU writing tecdar-imu/1 on a pty). The physics runs in slices (sim.robot.PHYSICS_WAKE_S); each
    proprioception sample becomes the controller sample of its own cycle, so a state is stamped
    with when it was measured and delivered at most one slice late."""

    def __init__(self, spec: SimArmSpec):
        from tecdard.sim.board import Board, PtyDevice, PyWire
        from tecdard.sim.robot import PHYSICS_WAKE_S
        sim = spec.sim_spec
        self.device = PtyDevice(sim.pty_link)
        self.robot = sim.build(wire=PyWire(Board(sim.board), self.device))
        self.robot.sync_clock()
        self.slice_s = PHYSICS_WAKE_S
        self.q, self.qd = list(self.robot.q), [0.0] * len(self.robot.q)
        self._ramp = JointArm(self.q)          # speedJ's acceleration-bounded rate, the simulator's command
        self._next_slice = time.monotonic()
        self.moved_t: float | None = None

    def speedj(self, qd, accel: float) -> None:
        self._ramp.speedj(qd, accel)

    def stop(self, decel: float) -> None:
        self._ramp.stop(decel)

    def halt(self) -> None:
        self._ramp.halt()

    def step(self, dt: float, now: float) -> list[tuple]:
        self._ramp.step(dt, now)
        self.robot.command_at(now, np.array(self._ramp.qd))
        if now < self._next_slice:
            return []
        self._next_slice = now + self.slice_s
        self.robot.advance_to(now)
        out = []
        for js in self.robot.drain_states():
            # the simulator's world is the UR model's, the controller's base frame (robots.model.UR_ARMS)
            force = js.tcp_force if js.tcp_force is not None else np.zeros(3)
            out.append((js.t, list(js.q), list(js.qd), tuple(force)))
            if self.moved_t is None and np.any(js.qd != 0.0):
                self.moved_t = js.t
        if out:
            self.q, self.qd = out[-1][1], out[-1][2]
        return out

    def truth(self):
        return self.robot.truth()

    def close(self) -> None:
        self.robot.hold()
        self.device.close()


# -- the script port and ur-rtde's control script ---------------------------------------------------

# ur-rtde's control script (rtde_control.script): output_int_register_0 says where it is
SCRIPT_READY, SCRIPT_DONE = 1, 2
STREAMED = {6, 9, 10, 11, 24}       # force mode, speedJ, speedL, servoJ, servoL: a new target each cycle
SPEEDJ, SPEED_STOP, STOPJ, SET_WATCHDOG, STOP_SCRIPT = 9, 15, 34, 35, 255
RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSED = 1, 2, 4


class JointArm:
    """The fake's arm under speedj: each joint's rate moves to its target at the commanded
    acceleration, the positions integrate the rates, every controller cycle."""

    def __init__(self, q, max_qd_rad_s: float = 3.14):
        self.q = [float(x) for x in q]
        self.qd = [0.0] * len(self.q)
        self.target = [0.0] * len(self.q)
        self.accel = 1.0
        self.max_qd = max_qd_rad_s
        self.moved_t: float | None = None     # when a joint first moved (monotonic), for the latency figure

    def speedj(self, qd, accel: float) -> None:
        self.target = [max(-self.max_qd, min(self.max_qd, float(x))) for x in qd]
        self.accel = max(float(accel), 1e-6)

    def stop(self, decel: float) -> None:
        self.speedj([0.0] * len(self.q), decel)

    def halt(self) -> None:
        """A protective stop: the rates go to zero at once (the brakes' reaction is not modelled)."""
        self.qd = [0.0] * len(self.q)
        self.target = [0.0] * len(self.q)

    def step(self, dt: float, now: float) -> list[tuple]:
        """One controller cycle; its sample (t, q, qd, TCP force in the base frame or None: not modelled)."""
        step = self.accel * dt
        for i, (v, goal) in enumerate(zip(self.qd, self.target)):
            v += max(-step, min(step, goal - v))
            self.qd[i] = v
            self.q[i] += v * dt
        if self.moved_t is None and any(self.qd):
            self.moved_t = now
        return [(now, list(self.q), list(self.qd), None)]

    def close(self) -> None:
        pass


class ControlScript:
    """ur-rtde's control script as the controller would run it: every cycle it reads the command
    in input_int_register_0 and signals in output_int_register_0 (rtde_control.script's main loop)."""

    def __init__(self, controller: "ControllerState", rtde: RtdeServer, arm: JointArm):
        self.controller, self.rtde, self.arm = controller, rtde, arm
        self.running = False
        self.executing = False
        self.commands: list[int] = []          # every command processed, in order
        self.speedj_t: collections.deque = collections.deque(maxlen=4096)   # (monotonic t, target) per new speedJ
        # rtde_set_watchdog on input_int_register_0: no input package for 1 / watchdog_hz s stops the program
        self.watchdog_hz = 0.0
        self.watchdog_trips = 0
        self._inputs_seen = -1
        self._last_input_t = time.monotonic()

    def start(self) -> None:
        self.running, self.executing = True, False
        self.watchdog_hz = 0.0                 # a new program sets its own
        self.controller.update(output_int_register_0=SCRIPT_READY)
        self.controller.set_program_running(True)

    def stop(self) -> None:
        self.running = False
        self.controller.set_program_running(False)

    def cycle(self, now: float) -> None:
        """The cycle due at `now`; the watchdog counts real time (a batch of cycles run late reads one input)."""
        if not self.running:
            return
        inputs, packages = self.rtde.read_inputs_counted()
        now = time.monotonic()
        if packages != self._inputs_seen:
            self._inputs_seen, self._last_input_t = packages, now
        elif self.watchdog_hz > 0 and now - self._last_input_t > 1.0 / self.watchdog_hz:
            self.watchdog_trips += 1           # the client went quiet: the controller stops the program
            self.arm.stop(10.0)
            self.stop()
            return
        cmd = inputs.get("input_int_register_0", 0)
        if cmd in STREAMED:
            self._process(cmd, inputs)
            self.controller.update(output_int_register_0=SCRIPT_READY)
        elif cmd == 0:
            self.executing = False
            self.controller.update(output_int_register_0=SCRIPT_READY)
        elif not self.executing:
            self.executing = True
            if self._process(cmd, inputs):
                self.controller.update(output_int_register_0=SCRIPT_DONE)

    def _process(self, cmd: int, inputs: dict) -> bool:
        """One command; False when it ends the script."""
        self.commands.append(cmd)
        reg = [inputs.get(f"input_double_register_{i}", 0.0) for i in range(8)]
        if cmd == SPEEDJ:
            if not self.speedj_t or self.speedj_t[-1][1] != tuple(reg[0:6]):
                self.speedj_t.append((time.monotonic(), tuple(reg[0:6])))
            self.arm.speedj(reg[0:6], reg[6])
        elif cmd in (SPEED_STOP, STOPJ):
            self.arm.stop(reg[0] if reg[0] > 0 else 10.0)
        elif cmd == SET_WATCHDOG:
            self.watchdog_hz = reg[0]
        elif cmd == STOP_SCRIPT:
            self.arm.stop(10.0)
            self.stop()
            return False
        return True


class ScriptServer(_TcpServer):
    """The script port (30003): URScript arrives as text; a program that defines `rtde_control`
    starts the control script. Other programs are recorded, not run."""

    conn_timeout_s = 0.05          # a pause this long ends a program

    def __init__(self, host: str, on_script, port: int = SCRIPT_PORT):
        self.on_script = on_script
        self.scripts: list[str] = []
        self._listen(host, port, "script")

    def _serve(self, conn: socket.socket) -> None:
        """A program is complete when the sender pauses: the controller runs what it has."""
        buf = b""
        try:
            while not self.stopped.is_set():
                try:
                    chunk = conn.recv(65536)
                    if not chunk:
                        break
                    buf += chunk
                except socket.timeout:
                    if buf:
                        self._program(buf)
                        buf = b""
        finally:
            if buf:
                self._program(buf)

    def _program(self, data: bytes) -> None:
        text = data.decode(errors="replace")
        self.scripts.append(text)
        self.on_script(text)


# -- the fake as a process of its own ---------------------------------------------------------

def free_loopback_host(ports=(DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT)) -> str:
    """A 127.0.0.x address whose fixed controller ports are free (tests never meet on them)."""
    import random
    for x in random.sample(range(2, 255), 253):
        host = f"127.0.0.{x}"
        try:
            for port in ports:
                with socket.create_server((host, port)):
                    pass
            return host
        except OSError:
            continue
    raise RuntimeError("no free 127.0.0.x address for a fake controller")


STALL_S = 0.1                        # the fake's cycles further behind than this: caught up at once, not replayed


def _child(host: str, arm_name: str, version, q, tcp_offset, sim, remote_control: bool, conn) -> None:
    """The fake controller's process: the arm and the control script step every controller cycle,
    which publishes its sample; it serves until told to stop, and answers the test's requests."""
    kinematics = UrKinematics(arm_name, tcp_offset)
    arm = JointArm(q) if sim is None else SimArm(sim)
    model = arm_name.rstrip("e")                  # the dashboard's name: UR5 for a UR5 or a UR5e
    controller = ControllerState({"actual_q": list(arm.q), "target_q": list(arm.q), "actual_qd": [0.0] * 6,
                                  "robot_mode": 7, "safety_mode": 1, "safety_status_bits": 1 << NORMAL_MODE_BIT,
                                  "robot_status_bits": 1 << POWER_ON_BIT, "runtime_state": RUNTIME_STOPPED,
                                  "speed_scaling": 1.0}, model=model, version=version,
                                 remote_control=remote_control)
    rtde = RtdeServer(host, controller, version=version)
    script = ControlScript(controller, rtde, arm)

    def on_script(text: str) -> None:
        if "def rtde_control():" in text:
            script.start()

    scripts = ScriptServer(host, on_script)
    dashboard = DashboardServer(host, controller, on_stop=script.stop)
    stop = threading.Event()
    period = 1.0 / rtde.max_frequency_hz
    t0 = time.monotonic() - CONTROLLER_UPTIME_S       # the controller was switched on a while before

    lies: list = []                 # (until, lie) the test asked for: what the controller reports instead
    late = {"worst_s": 0.0}         # the cycles' worst lateness since the test last asked (a loaded machine's stall)

    def sample(t: float, q, qd, force_base) -> None:
        """One cycle's state: its clock counts whole cycles since it started, as the real one does.
        `force_base` None: the TCP force stays what the test set. A lie in force changes it."""
        force = {} if force_base is None else {"actual_TCP_force": list(force_base) + [0.0] * 3}
        stamp = round((t - t0) / period) * period
        lie = next((lie for until, lie in lies if time.monotonic() < until), None)
        if lie is None:
            pose, speed = kinematics.pose_speed(q, qd)
            controller.publish(stamp, actual_q=list(q), target_q=list(q), actual_qd=list(qd),
                               actual_TCP_pose=pose, actual_TCP_speed=speed, **force)
            return
        if lie.get("freeze"):
            last = controller.samples[-1][1]
            controller.publish(last["timestamp"], **{k: v for k, v in last.items() if k not in ("timestamp", "_due")})
            return
        pose, speed = kinematics.pose_speed(q, qd)
        told = {"actual_q": list(q), "actual_qd": list(qd), "actual_TCP_pose": pose, "actual_TCP_speed": speed,
                **force}
        for name, joints in lie.get("values", {}).items():
            for j, value in joints.items():
                told[name][int(j)] = value
        controller.publish(stamp, delay_s=lie.get("delay_s", 0.0), target_q=list(q), **told)

    def cycle(t: float) -> None:
        script.cycle(t)
        if controller.values.get("safety_mode") != 1:
            arm.halt()                    # a protective or emergency stop halts the arm
        for ts, q, qd, force in arm.step(period, t):
            sample(ts, q, qd, force)

    def run_cycles() -> None:
        """Every cycle at its own time on an absolute schedule. A wake-up that comes late (the GIL held by RTDE's
        senders, the machine's load) runs every cycle that came due meanwhile at once, each at its own time, so
        the lateness stays that of one wake-up and never drifts; a stall past STALL_S is given up on."""
        t_next = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            late["worst_s"] = max(late["worst_s"], now - t_next)
            if now - t_next > STALL_S:
                t_next = now
            while t_next <= now:
                cycle(t_next)
                t_next += period
            delay = t_next - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    cycles = threading.Thread(target=run_cycles, name="controller-cycle", daemon=True)
    cycles.start()
    conn.send("ready")
    try:
        while True:
            msg = conn.recv()
            if msg[0] == "stop":
                break
            if msg[0] == "set":
                controller.update(**msg[1])
                if msg[1].get("safety_mode", 1) != 1 and script.running:
                    # a protective stop pauses the program, as PolyScope does
                    script.stop()
                    controller.update(runtime_state=RUNTIME_PAUSED)
                conn.send(None)
            elif msg[0] == "lie":
                lies.append((time.monotonic() + msg[2], msg[1]))
                conn.send(None)
            elif msg[0] == "inputs":
                conn.send((rtde.read_inputs(), rtde.input_packages))
            elif msg[0] == "dashboard":
                conn.send((list(dashboard.commands), list(dashboard.not_understood)))
            elif msg[0] == "arm":
                conn.send({"q": list(arm.q), "qd": list(arm.qd), "commands": list(script.commands),
                           "scripts": len(scripts.scripts), "program_running": script.running,
                           "watchdog_hz": script.watchdog_hz, "watchdog_trips": script.watchdog_trips,
                           "speedj_t": list(script.speedj_t), "moved_t": arm.moved_t, "popup": controller.popup,
                           "robot_mode": controller.snapshot().get("robot_mode")})
            elif msg[0] == "truth":
                conn.send(arm.truth() if sim is not None else None)
            elif msg[0] == "late":
                conn.send(late["worst_s"])
                late["worst_s"] = 0.0
    except EOFError:
        pass
    finally:
        stop.set()
        cycles.join(1.0)
        arm.close()
        dashboard.close()
        scripts.close()
        rtde.close()


def wait_for(predicate, timeout_s: float = 5.0) -> bool:
    """Poll `predicate` until it holds or `timeout_s` has passed; its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


class FakeController:
    """The parent's handle on a fake controller process at `host`: a UR arm (`arm`: UR3, UR5, UR10
    (CB3) or UR3e, UR5e, UR10e, UR16e) whose controller version defaults to its series', with the
    controller's TCP set to `tcp_offset` (x, y, z m, rotation vector rad, flange frame, as on the
    pendant). The arm integrates speedJ from `q`, or with `sim` (a SimArmSpec) is our simulator."""

    def __init__(self, host: str, arm: str = "UR5e", version=None, q=(0.0, -1.57, 1.57, -1.57, -1.57, 0.0),
                 tcp_offset=(0.0,) * 6, sim: "SimArmSpec | None" = None, remote_control: bool = True):
        import multiprocessing
        ctx = multiprocessing.get_context("spawn")
        self.host = host
        self.version = version or (E_SERIES_VERSION if arm.endswith("e") else CB3_VERSION)
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_child, args=(host, arm, self.version, list(q), list(tcp_offset), sim,
                                                      remote_control, child),
                                 name=f"fake-ur-{host}", daemon=True)
        self._proc.start()
        if not self._conn.poll(60.0) or self._conn.recv() != "ready":
            self.close()
            raise RuntimeError(f"the fake controller at {host} did not start")

    def truth(self):
        """With `sim`: the simulated world's truth (sim.world.SimTruth) now."""
        self._conn.send(("truth",))
        return self._conn.recv()

    def worst_late_s(self) -> float:
        """How far the controller's cycles fell behind their schedule at worst since the last call, s: the machine's
        load stalling the fake (its arm, its samples and the simulated board's stream), not anything the client did."""
        self._conn.send(("late",))
        return self._conn.recv()

    def set(self, **values) -> None:
        """Set output variables of the controller's state (robot_mode, safety_status_bits, actual_q ...)."""
        self._conn.send(("set", values))
        self._conn.recv()

    def lie(self, duration_s: float, values: dict | None = None, delay_s: float = 0.0, freeze: bool = False) -> None:
        """For `duration_s` from now, the controller reports what it should not:
        - `values`: {variable: {index: value}} in place of the arm's (actual_q {1: 7.0}: the shoulder
          at 7 rad; nan works too);
        - `delay_s`: every sample reaches RTDE's clients this late (and those after it, in order);
        - `freeze`: the same sample again, its timestamp unchanged."""
        self._conn.send(("lie", {"values": values or {}, "delay_s": delay_s, "freeze": freeze}, duration_s))
        self._conn.recv()

    def inputs(self) -> tuple[dict, int]:
        """The input variables the client wrote (latest values) and how many data packages it sent."""
        self._conn.send(("inputs",))
        return self._conn.recv()

    def arm(self) -> dict:
        """The arm's joint positions and rates, the control script's commands processed, the
        programs received, and whether the control script runs."""
        self._conn.send(("arm",))
        return self._conn.recv()

    def dashboard_commands(self) -> tuple[list[str], list[str]]:
        """The command lines the dashboard server has received, in order, and those it did not understand."""
        self._conn.send(("dashboard",))
        return self._conn.recv()

    def close(self) -> None:
        try:
            self._conn.send(("stop",))
        except (OSError, BrokenPipeError):
            pass
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.kill()
