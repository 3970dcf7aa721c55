"""Robot/PLC handshake over Modbus TCP (pymodbus): the PLC is the server, the station a polling client.

Roles: the PLC owns the registers and serves them (PLCs are Modbus servers out of the box: Siemens
MB_SERVER, Rockwell, Beckhoff, CODESYS), the station connects to it and polls. The PLC program then only
maps a data block and needs no client code; the station notices a dead PLC at its next request and a
PLC notices a dead station by its heartbeat counter standing still.

Register map (holding registers, 0-based protocol addresses; Modicon number = 40001 + address), with the
default bases; docs/plc.md has the handshake diagram and the PLC's side of it:

=========  ==================  =========  ===============================================================
address    name                written by meaning
=========  ==================  =========  ===============================================================
0          STATUS              station    0 offline, 1 ready, 2 busy, 3 done, 4 fault
1          VERDICT             station    with STATUS=done: 1 pass, 2 fail, 3 invalid, 4 indeterminate (else 0)
2          FAULT_CODE          station    with STATUS=fault: FAULT_CODES value (else 0)
3          HEARTBEAT           station    +1 (mod 65536) at least every second while the station runs
4          CYCLE               station    +1 (mod 65536) for every facet answered (done or fault)
5          SEQUENCE_ECHO       station    the PLC's SEQUENCE of the facet being answered
6          WARNINGS            station    with STATUS=done or fault: warning bits, bit 0 = drift alarm (done
                                          only), bit 1 = line alarm (the line's health) (else 0)
100        FACET_PRESENT       PLC        1: a facet waits for inspection (the request), 0: none
101        ACK                 PLC        1: the PLC has read the done/fault answer
102        DUMP_REQUEST        PLC        1: write a full data dump of this facet
103        RECIPE_CODE         PLC        facet type code (0 none; names from the station's table)
104        SEQUENCE            PLC        any number the PLC gives the facet (echoed back)
105..114   SERIAL              PLC        serial number, ASCII, 2 characters per register, high byte
                                          first, padded with NUL or spaces (20 characters)
115..122   RECIPE_NAME         PLC        recipe name, same encoding (16 characters; wins over the code)
=========  ==================  =========  ===============================================================
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from datetime import datetime

from ...errors import TriggerError
from ..protocols import FacetRequest
from ._handshake import ANSWERED, BUSY, CLOSED, IDLE, READY, REQUESTED, PolledHandshake, pace, recipe_name

log = logging.getLogger(__name__)
# pymodbus logs every failed connect and request itself ("Connection to (host, port) failed"), which the
# TriggerError raised here says with what to do: during a PLC outage those lines only filled the log.
logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

# STATUS values (station -> PLC).
OFFLINE, STATUS_READY, STATUS_BUSY, STATUS_DONE, STATUS_FAULT = 0, 1, 2, 3, 4
#: VERDICT values (station -> PLC).
VERDICT_CODES = {"pass": 1, "fail": 2, "invalid": 3, "indeterminate": 4}

# Offsets in the station's block.
STATUS, VERDICT, FAULT_CODE, HEARTBEAT, CYCLE, SEQUENCE_ECHO, WARNINGS = range(7)
STATION_REGISTERS = 7
# Offsets in the PLC's block.
FACET_PRESENT, ACK, DUMP_REQUEST, RECIPE_CODE, SEQUENCE, SERIAL = range(6)


@dataclass(frozen=True)
class RegisterMap:
    """Where the two register blocks are and how long the text fields are.

    Parameters
    ----------
    station_base : int
        Protocol address of STATUS, the first register the station writes.
    plc_base : int
        Protocol address of FACET_PRESENT, the first register the PLC writes.
    serial_registers : int
        Registers of the serial number (2 ASCII characters each).
    recipe_name_registers : int
        Registers of the recipe name (2 ASCII characters each); 0 = no recipe name field.
    """

    station_base: int = 0
    plc_base: int = 100
    serial_registers: int = 10
    recipe_name_registers: int = 8

    def __post_init__(self):
        if not 1 <= self.serial_registers <= 60 or not 0 <= self.recipe_name_registers <= 60:
            raise ValueError("serial_registers must be 1..60 and recipe_name_registers 0..60")
        st = range(self.station_base, self.station_base + STATION_REGISTERS)
        plc = range(self.plc_base, self.plc_base + self.plc_registers)
        if min(st.start, plc.start) < 0 or max(st.stop, plc.stop) > 0x10000:
            raise ValueError("register blocks must lie within addresses 0..65535")
        if st.start < plc.stop and plc.start < st.stop:
            raise ValueError(f"station block {st.start}..{st.stop - 1} overlaps PLC block "
                             f"{plc.start}..{plc.stop - 1}")

    @property
    def recipe_name_offset(self) -> int:
        """Offset of RECIPE_NAME in the PLC's block."""
        return SERIAL + self.serial_registers

    @property
    def plc_registers(self) -> int:
        """Length of the PLC's block (registers)."""
        return SERIAL + self.serial_registers + self.recipe_name_registers


def encode_ascii(text: str, registers: int) -> list[int]:
    """Pack ``text`` into ``registers`` 16-bit registers, 2 characters each, high byte first, NUL-padded.

    Raises ValueError when it does not fit or is not ASCII.
    """
    raw = text.encode("ascii")
    if len(raw) > 2 * registers:
        raise ValueError(f"{text!r} does not fit in {registers} registers ({2 * registers} characters)")
    raw = raw.ljust(2 * registers, b"\0")
    return [(raw[i] << 8) | raw[i + 1] for i in range(0, len(raw), 2)]


def decode_ascii(registers: list[int]) -> str:
    """Unpack text packed by :func:`encode_ascii`: stops at the first NUL, strips spaces; a byte that
    is not printable ASCII reads as "?"."""
    raw = bytearray()
    for reg in registers:
        raw += bytes(((reg >> 8) & 0xFF, reg & 0xFF))
    raw = raw.split(b"\0", 1)[0]
    return "".join(chr(b) if 32 <= b < 127 else "?" for b in raw).strip()


class ModbusTrigger(PolledHandshake):
    """Trigger backend: the station as Modbus TCP client of the PLC (see module doc and docs/plc.md).

    Connects at construction. Every I/O failure (connection refused, lost, request timed out, exception
    response) raises TriggerError and closes the trigger; :meth:`reopen` (or a new object) connects
    again.

    Parameters
    ----------
    host : str
        PLC address.
    port : int
        PLC's Modbus TCP port.
    unit_id : int
        Modbus unit (device) id the PLC answers to.
    register_map : RegisterMap, optional
        Register layout; the documented defaults if None.
    recipes : dict of int to str, optional
        Recipe code -> recipe name.
    timeout_s : float
        Time allowed to connect and for each Modbus request, seconds.
    ack_timeout_s : float
        Time the PLC has to acknowledge a done/fault answer, seconds.
    poll_interval_s : float
        Time between two reads of the PLC's block while waiting, seconds.
    heartbeat_interval_s : float
        While the trigger itself waits (for a facet or an acknowledgement) it beats the heartbeat at
        least this often, seconds.
    """

    def __init__(self, host: str, port: int = 502, *, unit_id: int = 1,
                 register_map: RegisterMap | None = None, recipes: dict[int, str] | None = None,
                 timeout_s: float = 1.0, ack_timeout_s: float = 5.0, poll_interval_s: float = 0.02,
                 heartbeat_interval_s: float = 0.5):
        super().__init__()
        self.host, self.port, self.unit_id = host, int(port), int(unit_id)
        self.name = f"PLC at {host}:{self.port}"
        self.map = register_map or RegisterMap()
        self.recipes = dict(recipes or {})
        self.timeout_s = float(timeout_s)
        self.ack_timeout_s = float(ack_timeout_s)
        self.poll_interval_s = float(poll_interval_s)
        self.heartbeat_interval_s = float(heartbeat_interval_s)
        #: SEQUENCE of the last request taken. Kept across reconnects (reopen()): after an answer the PLC
        #: acknowledged too late (the station had given up and reconnected), a request with another SEQUENCE
        #: is the next facet, not a leftover of the interrupted cycle (docs/plc.md, rule 3).
        self._last_sequence: int | None = None
        self._connect()

    def _connect(self) -> None:
        # optional: the PLC's driver (pymodbus, ~75 ms CPU), loaded only when this trigger is chosen
        from pymodbus.client import ModbusTcpClient

        self._state = IDLE
        self._regs = [0] * STATION_REGISTERS
        self._armed = False         # FACET_PRESENT seen at 0 since the last request: a 1 is a new one
        self._stale_warned = False
        self._request: FacetRequest | None = None
        self._last_beat = time.monotonic()
        self._client = ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=0,
                                       reconnect_delay=0, reconnect_delay_max=0)
        try:
            ok = self._client.connect()
        except Exception as exc:  # pymodbus/OS errors alike
            ok, why = False, f"{type(exc).__name__}: {exc}"
        else:
            why = "connection refused or timed out"
        if not ok:
            self._client.close()
            self._state = CLOSED
            raise TriggerError(f"cannot connect to the {self.name} ({why} after {self.timeout_s:g} s): "
                               "check that the PLC is on, its Modbus TCP server enabled and the address "
                               "in station.toml; the station retries later")
        try:
            # Continue the PLC-visible counters from where a previous connection left them, so that
            # the PLC's heartbeat watchdog sees them keep moving across a reconnect.
            old = self._read(self.map.station_base, STATION_REGISTERS, "reading the station block")
            self._regs[HEARTBEAT], self._regs[CYCLE] = old[HEARTBEAT], old[CYCLE]
            self._write("writing the station block")
            self._read_plc("reading the PLC block")  # a wrong map shows now, not at the first facet
        except TriggerError:
            self.close()
            raise
        log.info("connected to the %s (unit %d, station block at %d, PLC block at %d)", self.name,
                 self.unit_id, self.map.station_base, self.map.plc_base)

    def reopen(self) -> ModbusTrigger:
        """Close (if not yet) and connect again: the station's recovery after a TriggerError.

        Returns self. Raises TriggerError when the PLC is still unreachable; the trigger then stays
        closed and ``reopen`` may be called again later.
        """
        self.close()
        self._connect()
        return self

    # Modbus I/O ----------------------------------------------------------------------------------

    def _fail(self, what: str, why: str) -> TriggerError:
        self._client.close()
        self._state = CLOSED
        return TriggerError(f"{self.name}: {what} failed ({why}): the PLC or the network is down or "
                            "the PLC dropped the connection; the station reports it and reconnects "
                            "(reopen() or a new trigger)")

    def _read(self, address: int, count: int, what: str) -> list[int]:
        try:
            rr = self._client.read_holding_registers(address, count=count, device_id=self.unit_id)
        except Exception as exc:  # ConnectionException, ModbusIOException, OSError
            raise self._fail(what, f"{type(exc).__name__}: {exc}") from exc
        if rr.isError():
            raise self._refused(what, rr)
        if len(rr.registers) < count:
            raise self._refused(what, f"{len(rr.registers)} registers instead of {count}")
        return list(rr.registers[:count])

    def _write(self, what: str) -> None:
        try:
            rr = self._client.write_registers(self.map.station_base, list(self._regs), device_id=self.unit_id)
        except Exception as exc:
            raise self._fail(what, f"{type(exc).__name__}: {exc}") from exc
        if rr.isError():
            raise self._refused(what, rr)

    def _refused(self, what: str, rr) -> TriggerError:
        self._client.close()
        self._state = CLOSED
        return TriggerError(
            f"{self.name} refused or garbled {what} ({rr}): check the register map (station block at "
            f"{self.map.station_base}, {STATION_REGISTERS} registers; PLC block at {self.map.plc_base}, "
            f"{self.map.plc_registers} registers; unit id {self.unit_id}) against the PLC program and "
            "docs/plc.md")

    def _read_plc(self, what: str) -> list[int]:
        return self._read(self.map.plc_base, self.map.plc_registers, what)

    def _beat(self) -> None:
        self._regs[HEARTBEAT] = (self._regs[HEARTBEAT] + 1) & 0xFFFF
        self._write("writing the heartbeat")
        self._last_beat = time.monotonic()

    # Trigger protocol ----------------------------------------------------------------------------

    def ready(self) -> None:
        """STATUS = ready (verdict and fault code cleared)."""
        self._enter("ready", (IDLE, READY, ANSWERED))
        # The PLC may raise FACET_PRESENT only once it sees READY: read it before writing READY, so that
        # a 0 now makes any later 1 a new request, and a 1 now is a request left from an earlier cycle.
        plc = self._read_plc("reading the PLC block")
        self._armed = self._armed or not plc[FACET_PRESENT] or self._new_sequence(plc)
        self._regs[STATUS], self._regs[VERDICT], self._regs[FAULT_CODE] = STATUS_READY, 0, 0
        self._regs[WARNINGS] = 0
        self._write("writing STATUS=ready")
        self._request = None
        self._state = READY

    def wait_for_facet(self, timeout_s: float) -> FacetRequest | None:
        """Poll the PLC's block for a new request (FACET_PRESENT 0 -> 1 with ACK = 0) for up to
        ``timeout_s`` seconds; None if none came."""
        self._enter("wait_for_facet", (READY,))
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        while True:
            plc = self._read_plc("reading the PLC block")
            if not plc[FACET_PRESENT]:
                self._armed, self._stale_warned = True, False
            elif (self._armed or self._new_sequence(plc)) and not plc[ACK]:
                return self._take(plc)
            elif not self._stale_warned:
                self._stale_warned = True
                log.warning("%s: FACET_PRESENT is 1 %s; waiting for the PLC to set it to 0 and raise "
                            "it again for a new facet", self.name,
                            "with ACK still 1" if self._armed else
                            "already when the station became ready (a request from an interrupted cycle)")
            if time.monotonic() >= deadline:
                return None
            self._maybe_beat()
            pace(deadline, self.poll_interval_s)

    def _new_sequence(self, plc: list[int]) -> bool:
        """FACET_PRESENT is 1 with a SEQUENCE other than the last request's: a new facet, although the station
        never saw FACET_PRESENT at 0. The PLC acknowledged and raised the next request between two polls, or
        acknowledged after the station had given up waiting and reconnected (the SEQUENCE outlives reconnects).
        A request left up from the interrupted cycle itself keeps its SEQUENCE and stays stale.
        """
        fresh = (self._last_sequence is not None and bool(plc[FACET_PRESENT])
                 and plc[SEQUENCE] != self._last_sequence)
        if fresh and not self._armed:
            log.info("%s: a new request (SEQUENCE %d) was raised right after the answer to SEQUENCE %d: taken",
                     self.name, plc[SEQUENCE], self._last_sequence)
            self._armed = True
        return fresh

    def _take(self, plc: list[int]) -> FacetRequest:
        m = self.map
        serial = decode_ascii(plc[SERIAL:SERIAL + m.serial_registers])
        name = decode_ascii(plc[m.recipe_name_offset:m.recipe_name_offset + m.recipe_name_registers])
        extra = {"backend": "modbus", "plc": self.name, "sequence": plc[SEQUENCE],
                 "recipe_code": plc[RECIPE_CODE]}
        if not serial:
            serial = f"PLC-NOSERIAL-{datetime.now():%Y%m%d-%H%M%S}-{plc[SEQUENCE]:05d}"
            extra["serial_missing"] = True
            log.warning("%s raised FACET_PRESENT with an empty SERIAL: using %s", self.name, serial)
        self._request = FacetRequest(serial=serial, recipe=recipe_name(plc[RECIPE_CODE], name, self.recipes),
                                     dump=bool(plc[DUMP_REQUEST]), extra=extra)
        self._armed = False
        self._last_sequence = plc[SEQUENCE]
        self._state = REQUESTED
        log.debug("%s: facet %s (sequence %d, recipe %r, dump %s)", self.name, serial, plc[SEQUENCE],
                  self._request.recipe, self._request.dump)
        return self._request

    def busy(self) -> None:
        """STATUS = busy, SEQUENCE_ECHO = the request's SEQUENCE."""
        self._enter("busy", (REQUESTED,))
        self._regs[STATUS] = STATUS_BUSY
        self._regs[SEQUENCE_ECHO] = self._request.extra["sequence"]
        self._write("writing STATUS=busy")
        self._state = BUSY

    def done(self, verdict: str, warnings: int = 0) -> None:
        """VERDICT, WARNINGS (the WARNING_BITS), STATUS = done, CYCLE + 1, in one write; returns once the
        PLC acknowledged (ACK = 1), else raises TriggerError after ``ack_timeout_s``."""
        self._enter("done", (BUSY,))
        self._check_verdict(verdict)
        self._regs[VERDICT], self._regs[FAULT_CODE] = VERDICT_CODES[verdict], 0
        self._regs[WARNINGS] = int(warnings) & 0xFFFF
        self._answer(STATUS_DONE, f"done ({verdict})")

    def fault(self, code: int, reason: str, warnings: int = 0) -> None:
        """FAULT_CODE, WARNINGS (the WARNING_BITS: the line's health), STATUS = fault, CYCLE + 1; returns once the
        PLC acknowledged (ACK = 1), else raises TriggerError after ``ack_timeout_s``. The reason goes to the log
        (the PLC gets the code)."""
        self._enter("fault", (BUSY,))
        code = self._check_fault_code(code)
        log.warning("%s: fault %d for facet %s: %s", self.name, code, self._request.serial, reason)
        self._regs[VERDICT], self._regs[FAULT_CODE], self._regs[WARNINGS] = 0, code, int(warnings) & 0xFFFF
        self._answer(STATUS_FAULT, f"fault ({code})")

    def _answer(self, status: int, what: str) -> None:
        self._regs[STATUS] = status
        self._regs[CYCLE] = (self._regs[CYCLE] + 1) & 0xFFFF
        self._write(f"writing the {what} answer")
        self._state = ANSWERED

        answered = self._request.extra["sequence"]

        def poll():
            plc = self._read_plc("waiting for ACK")
            new_request = bool(plc[FACET_PRESENT]) and plc[SEQUENCE] != answered
            if plc[ACK] or new_request:       # a new SEQUENCE raised means the answer was read (ACK missed)
                return (not plc[FACET_PRESENT]) or new_request
            return None

        self._await_ack(poll, what, f"ACK, register {self.map.plc_base + ACK}, stayed 0", "its connection")

    def heartbeat(self) -> None:
        """HEARTBEAT + 1 (mod 65536)."""
        self._enter("heartbeat", (IDLE, READY, REQUESTED, BUSY, ANSWERED))
        self._beat()

    def close(self) -> None:
        """STATUS = offline (if the PLC is still reachable), then disconnect. Idempotent."""
        if self._state != CLOSED:
            self._regs[STATUS], self._regs[VERDICT], self._regs[FAULT_CODE] = OFFLINE, 0, 0
            try:
                self._write("writing STATUS=offline")
            except TriggerError as exc:
                log.debug("%s: could not write STATUS=offline on close: %s", self.name, exc)
        self._client.close()
        self._state = CLOSED
