"""Robot/PLC handshake over USB digital I/O: an FTDI FT232R or FT232H in asynchronous bit-bang mode (pyusb).

The chip's eight data pins D0..D7 (FT232H: ADBUS0..7) become 4 outputs and 4 inputs, wired to the PLC's
digital inputs and outputs through an interface board (optocouplers or a level shifter: the chip is a
3.3 V/5 V TTL part, PLCs are 24 V). Eight pins cannot carry eleven one-line-per-signal handshake lines, so
the station's state is a 3-bit code on three outputs (all pins change together, in one USB write):

====  =====  ===========  ===========================================================================
pin   UART   direction    signal
====  =====  ===========  ===========================================================================
D0    TXD    out          STATUS bit 0
D1    RXD    out          HEARTBEAT: toggles at least every second while the station runs
D2    RTS#   out          STATUS bit 1
D3    CTS#   in           FACET_PRESENT: 1 = a facet waits for inspection (the request); 0 = acknowledge
D4    DTR#   out          STATUS bit 2
D5    DSR#   in           DUMP_REQUEST: 1 = write a full data dump of this facet
D6    DCD#   in           RECIPE bit 0
D7    RI#    in           RECIPE bit 1
====  =====  ===========  ===========================================================================

STATUS code (bit 2, bit 1, bit 0): 0 offline, 1 ready, 2 busy, 3 done-pass, 4 done-fail, 5 done-invalid,
6 fault, 7 done-indeterminate (the guarded decision rule could not decide). The station's outputs are
UART outputs idling high when the chip is not in bit-bang mode, so 7 without a toggling heartbeat means
"no station driving the pins". The code is only valid while the heartbeat toggles. Outputs sit on the pins that are
outputs in the chip's UART mode and inputs on pins
that are inputs there, so that before the station configures bit-bang nothing drives against the PLC.

Discrete I/O carries no serial number: the station makes one, "USB-<YYYYMMDD>-<NNNN>" (see
:class:`~sofast_station.devices.triggers._handshake.SerialGenerator`). docs/plc.md has the handshake.

FTDI vendor requests used (the same as libftdi's): reset/purge (0x00), set baud rate (0x03), set latency
timer (0x09), set bit mode (0x0B, async bit-bang = 0x01 with the direction mask), read pins (0x0C, the
instantaneous pin levels); the output byte goes to the bulk OUT endpoint 0x02.
"""

from __future__ import annotations

import errno as _errno
import logging
import os
import time

from ...errors import ConfigError, TriggerError
from ..protocols import FacetRequest
from ._handshake import (ANSWERED, BUSY, CLOSED, IDLE, READY, REQUESTED, PolledHandshake, SerialGenerator, pace,
                         recipe_name)

log = logging.getLogger(__name__)

VENDOR_FTDI = 0x0403
#: Product ids of the supported chips.
PRODUCTS = {0x6001: "FT232R", 0x6014: "FT232H"}

# FTDI vendor requests (libftdi's names).
REQTYPE_OUT, REQTYPE_IN = 0x40, 0xC0
SIO_RESET, SIO_SET_BAUDRATE, SIO_SET_LATENCY_TIMER, SIO_SET_BITMODE, SIO_READ_PINS = 0x00, 0x03, 0x09, 0x0B, 0x0C
RESET_SIO, PURGE_RX, PURGE_TX = 0, 1, 2
BITMODE_RESET, BITMODE_BITBANG = 0x00, 0x01
INTERFACE_A = 1           # wIndex of channel A
EP_OUT, EP_IN = 0x02, 0x81
BAUD_9600 = 0x4138        # divisor for 9600 baud (3 MHz / 312.5): the bit-bang byte clock
LATENCY_MS = 2

# Pin map: outputs.
OUT_STATUS0, OUT_HEARTBEAT, OUT_STATUS1, OUT_STATUS2 = 1 << 0, 1 << 1, 1 << 2, 1 << 4
# Pin map: inputs.
IN_FACET_PRESENT, IN_DUMP_REQUEST, IN_RECIPE0, IN_RECIPE1 = 1 << 3, 1 << 5, 1 << 6, 1 << 7
#: Direction mask for SIO_SET_BITMODE: 1 = output.
OUTPUT_MASK = OUT_STATUS0 | OUT_HEARTBEAT | OUT_STATUS1 | OUT_STATUS2

# STATUS codes.
OFFLINE, STATUS_READY, STATUS_BUSY, DONE_PASS, DONE_FAIL, DONE_INVALID, STATUS_FAULT, DONE_INDETERMINATE = range(8)
DONE_CODES = {"pass": DONE_PASS, "fail": DONE_FAIL, "invalid": DONE_INVALID, "indeterminate": DONE_INDETERMINATE}


def status_pins(code: int) -> int:
    """The output pins (byte) that show STATUS ``code`` (0..7)."""
    return ((OUT_STATUS0 if code & 1 else 0) | (OUT_STATUS1 if code & 2 else 0)
            | (OUT_STATUS2 if code & 4 else 0))


def pins_status(pins: int) -> int:
    """The STATUS code (0..7) shown by the pin levels ``pins`` (byte)."""
    return ((1 if pins & OUT_STATUS0 else 0) | (2 if pins & OUT_STATUS1 else 0)
            | (4 if pins & OUT_STATUS2 else 0))


def _ctrl_timeout(timeout_s: float) -> int:
    return max(1, int(round(1000 * timeout_s)))


class UsbTrigger(PolledHandshake):
    """Trigger backend on an FTDI FT232R/FT232H in async bit-bang mode (see module doc and docs/plc.md).

    Opens the chip at construction. Every USB failure (unplugged, timed out, stalled) raises
    TriggerError and closes the trigger; :meth:`reopen` (or a new object) looks for the chip again.

    Parameters
    ----------
    serial_number : str, optional
        The chip's USB serial number (iSerialNumber, e.g. "A50285BI"); required when more than one
        FT232R/FT232H is plugged in (a station often has an FTDI serial cable too).
    product_id : int, optional
        0x6001 (FT232R) or 0x6014 (FT232H); either if None.
    backend : usb.backend.IBackend, optional
        pyusb backend; libusb 1.0 (pyusb's default search) if None. Tests pass a virtual one.
    recipes : dict of int to str, optional
        Recipe code (0..3, from the two recipe pins) -> recipe name.
    invert_inputs, invert_outputs : int
        Bit masks of pins whose level is inverted by the interface board (bit n = pin Dn).
    ack_timeout_s : float
        Time the PLC has to acknowledge done/fault by dropping FACET_PRESENT, seconds.
    poll_interval_s : float
        Time between two reads of the pins while waiting, seconds.
    heartbeat_interval_s : float
        While the trigger itself waits it toggles the heartbeat at least this often, seconds.
    usb_timeout_s : float
        Time allowed for each USB transfer, seconds.
    serial_prefix : str
        Prefix of the station-made serial numbers.
    counter_file : str or Path, optional
        Keeps the daily serial counter across restarts (put it under the station's data_dir).
    """

    def __init__(self, *, serial_number: str | None = None, product_id: int | None = None, backend=None,
                 recipes: dict[int, str] | None = None, invert_inputs: int = 0, invert_outputs: int = 0,
                 ack_timeout_s: float = 5.0, poll_interval_s: float = 0.01, heartbeat_interval_s: float = 0.5,
                 usb_timeout_s: float = 0.5, serial_prefix: str = "USB",
                 counter_file: str | os.PathLike | None = None):
        super().__init__()
        # optional: the USB I/O's driver (pyusb), loaded only when this trigger is chosen
        import usb.core
        import usb.util

        self._usb_core, self._usb_util = usb.core, usb.util
        self.name = "USB I/O"
        if product_id is not None and product_id not in PRODUCTS:
            raise ConfigError(f"product_id {product_id:#06x} is not an FT232R (0x6001) or FT232H (0x6014)")
        self.recipes = dict(recipes or {})
        self.invert_inputs, self.invert_outputs = int(invert_inputs) & 0xFF, int(invert_outputs) & 0xFF
        self.ack_timeout_s = float(ack_timeout_s)
        self.poll_interval_s = float(poll_interval_s)
        self.heartbeat_interval_s = float(heartbeat_interval_s)
        self._timeout_ms = _ctrl_timeout(usb_timeout_s)
        self.serials = SerialGenerator(serial_prefix, counter_file)
        self._find = {"serial_number": serial_number, "product_id": product_id, "backend": backend}
        self._dev = None
        self._open()

    def _open(self) -> None:
        # optional: the USB I/O's driver (pyusb), loaded only when this trigger is chosen
        import usb.core

        self._state = IDLE
        self._status, self._beat_level = OFFLINE, 0
        self._armed, self._stale_warned = False, False
        self._request: FacetRequest | None = None
        self._last_beat = time.monotonic()
        self._dev = None
        serial_number, product_id = self._find["serial_number"], self._find["product_id"]
        wanted = (product_id,) if product_id is not None else tuple(PRODUCTS)

        def match(dev) -> bool:
            if dev.idProduct not in wanted:
                return False
            if serial_number is None:
                return True
            try:
                return dev.serial_number == serial_number
            except (usb.core.USBError, ValueError):  # no access to the strings of a device not ours
                return False

        try:
            found = list(usb.core.find(find_all=True, backend=self._find["backend"], idVendor=VENDOR_FTDI,
                                       custom_match=match))
        except usb.core.NoBackendError as exc:
            self._state = CLOSED
            raise ConfigError("pyusb found no USB backend: install the libusb 1.0 library (Debian package "
                              f"libusb-1.0-0) on the station ({exc})") from exc
        kinds = "/".join(PRODUCTS[p] for p in wanted)
        self.name = f"USB I/O {kinds}" + (f" {serial_number}" if serial_number else "")
        if not found:
            self._state = CLOSED
            raise TriggerError(f"no FTDI {kinds} ({VENDOR_FTDI:04x}:{'/'.join(f'{p:04x}' for p in wanted)})"
                               + (f" with serial number {serial_number}" if serial_number else "")
                               + " on the USB bus: check the cable and the interface box's power; the "
                               "station retries later")
        if len(found) > 1:
            self._state = CLOSED
            raise ConfigError(f"{len(found)} FTDI {kinds} chips are plugged in: name the handshake's one "
                              "with serial_number= in station.toml (lsusb -v shows iSerial)")
        self._dev = found[0]
        self.name = f"USB I/O {PRODUCTS[self._dev.idProduct]} (bus {self._dev.bus}, address {self._dev.address})"
        try:
            self._setup()
        except Exception:
            self.close()
            raise
        log.info("opened %s in async bit-bang mode (direction mask %#04x)", self.name, OUTPUT_MASK)

    def reopen(self) -> UsbTrigger:
        """Close (if not yet) and look for the chip again: the station's recovery after a TriggerError.

        Returns self. Raises TriggerError while the chip is not back on the bus; the trigger then stays
        closed and ``reopen`` may be called again later.
        """
        self.close()
        self._open()
        return self

    # USB I/O -------------------------------------------------------------------------------------

    def _usb(self, what: str, fn, *args):
        try:
            return fn(*args)
        except self._usb_core.USBError as exc:
            self._state = CLOSED
            if getattr(exc, "errno", None) == _errno.EACCES:
                raise ConfigError(f"{self.name}: no permission to use the device ({exc}): install the udev "
                                  "rule from docs/plc.md or run the station in the plugdev group") from exc
            gone = getattr(exc, "errno", None) in (_errno.ENODEV, _errno.EIO, _errno.ENOENT)
            raise TriggerError(
                f"{self.name}: {what} failed ({exc}): "
                + ("the device disappeared (unplugged, cable, hub or interface box power)" if gone else
                   "the device stopped answering")
                + "; the station reports it and looks for the device again") from exc

    def _ctrl_out(self, request: int, value: int, index: int = INTERFACE_A) -> None:
        self._usb(f"FTDI request {request:#04x}", self._dev.ctrl_transfer, REQTYPE_OUT, request, value, index,
                  None, self._timeout_ms)

    def _setup(self) -> None:
        dev = self._dev
        try:
            attached = self._usb("checking for a kernel driver", dev.is_kernel_driver_active, 0)
        except NotImplementedError:  # backends without kernel drivers (Windows, macOS)
            attached = False
        if attached:  # ftdi_sio has it as /dev/ttyUSBn
            self._usb("detaching the kernel driver", dev.detach_kernel_driver, 0)
        try:
            dev.get_active_configuration()
        except self._usb_core.USBError:
            self._usb("setting the configuration", dev.set_configuration)
        self._usb("claiming interface 0", self._usb_util.claim_interface, dev, 0)
        self._ctrl_out(SIO_RESET, RESET_SIO)
        self._ctrl_out(SIO_SET_LATENCY_TIMER, LATENCY_MS)
        self._ctrl_out(SIO_SET_BAUDRATE, BAUD_9600, INTERFACE_A if dev.idProduct == 0x6014 else 0)
        self._ctrl_out(SIO_SET_BITMODE, BITMODE_RESET << 8)
        self._ctrl_out(SIO_SET_BITMODE, (BITMODE_BITBANG << 8) | OUTPUT_MASK)
        self._ctrl_out(SIO_RESET, PURGE_RX)
        self._ctrl_out(SIO_RESET, PURGE_TX)
        self._put(OFFLINE, "writing STATUS=offline")

    def read_pins(self) -> int:
        """The levels of D0..D7 as the station sees them (inputs after ``invert_inputs``), a byte."""
        data = self._usb("reading the pins", self._dev.ctrl_transfer, REQTYPE_IN, SIO_READ_PINS, 0, INTERFACE_A,
                         1, self._timeout_ms)
        if len(data) != 1:
            self._state = CLOSED
            raise TriggerError(f"{self.name}: read-pins answered {len(data)} bytes, not 1: not an FTDI "
                               "chip in bit-bang mode; the station reopens it")
        return data[0] ^ self.invert_inputs

    def _put(self, status: int, what: str) -> None:
        byte = (status_pins(status) | (OUT_HEARTBEAT if self._beat_level else 0)) ^ self.invert_outputs
        n = self._usb(what, self._dev.write, EP_OUT, bytes((byte,)), self._timeout_ms)
        if n != 1:
            self._state = CLOSED
            raise TriggerError(f"{self.name}: {what}: the chip took {n} bytes, not 1; the station reopens it")
        self._status = status

    def _beat(self) -> None:
        self._beat_level ^= 1
        self._put(self._status, "toggling the heartbeat")
        self._last_beat = time.monotonic()

    # Trigger protocol ----------------------------------------------------------------------------

    def ready(self) -> None:
        """STATUS = ready."""
        self._enter("ready", (IDLE, READY, ANSWERED))
        # The PLC raises FACET_PRESENT only once it sees READY: a 1 before it is a request left over.
        self._armed = self._armed or not self.read_pins() & IN_FACET_PRESENT
        self._put(STATUS_READY, "writing STATUS=ready")
        self._request = None
        self._state = READY

    def wait_for_facet(self, timeout_s: float) -> FacetRequest | None:
        """Poll the pins for a new request (FACET_PRESENT 0 -> 1) for up to ``timeout_s`` seconds; None
        if none came."""
        self._enter("wait_for_facet", (READY,))
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        while True:
            pins = self.read_pins()
            if not pins & IN_FACET_PRESENT:
                self._armed, self._stale_warned = True, False
            elif self._armed:
                return self._take(pins)
            elif not self._stale_warned:
                self._stale_warned = True
                log.warning("%s: FACET_PRESENT was already 1 when the station became ready (a request from "
                            "an interrupted cycle); waiting for the PLC to drop it and raise it again",
                            self.name)
            if time.monotonic() >= deadline:
                return None
            self._maybe_beat()
            pace(deadline, self.poll_interval_s)

    def _take(self, pins: int) -> FacetRequest:
        code = (1 if pins & IN_RECIPE0 else 0) | (2 if pins & IN_RECIPE1 else 0)
        serial = self.serials.next()
        self._request = FacetRequest(serial=serial, recipe=recipe_name(code, "", self.recipes),
                                     dump=bool(pins & IN_DUMP_REQUEST),
                                     extra={"backend": "usb", "device": self.name, "recipe_code": code,
                                            "pins": pins, "serial_source": "station"})
        self._armed = False
        self._state = REQUESTED
        log.debug("%s: facet request, serial %s, recipe code %d, dump %s", self.name, serial, code,
                  self._request.dump)
        return self._request

    def busy(self) -> None:
        """STATUS = busy."""
        self._enter("busy", (REQUESTED,))
        self._put(STATUS_BUSY, "writing STATUS=busy")
        self._state = BUSY

    def done(self, verdict: str, warnings: int = 0) -> None:
        """STATUS = done-pass/-fail/-invalid; returns once the PLC dropped FACET_PRESENT (its
        acknowledgement), else raises TriggerError after ``ack_timeout_s``. Every pin is taken, so
        ``warnings`` (a drift alarm) reaches only the log, the journal and the console (docs/plc.md)."""
        self._enter("done", (BUSY,))
        self._check_verdict(verdict)
        self._answer(DONE_CODES[verdict], f"done-{verdict}")

    def fault(self, code: int, reason: str, warnings: int = 0) -> None:
        """STATUS = fault (discrete I/O carries no fault code nor ``warnings``: ``code`` and ``reason`` go to the log);
        returns once the PLC dropped FACET_PRESENT, else raises TriggerError after ``ack_timeout_s``."""
        self._enter("fault", (BUSY,))
        code = self._check_fault_code(code)
        log.warning("%s: fault %d for facet %s: %s", self.name, code, self._request.serial, reason)
        self._answer(STATUS_FAULT, "fault")

    def _answer(self, status: int, what: str) -> None:
        self._put(status, f"writing STATUS={what}")
        self._state = ANSWERED
        self._await_ack(lambda: None if self.read_pins() & IN_FACET_PRESENT else True, what,
                        "FACET_PRESENT, pin D3/CTS#, stayed 1", "the wiring")

    def heartbeat(self) -> None:
        """Toggle the HEARTBEAT pin."""
        self._enter("heartbeat", (IDLE, READY, REQUESTED, BUSY, ANSWERED))
        self._beat()

    def close(self) -> None:
        """STATUS = offline (if the chip is still there; the pins stay in bit-bang mode holding it), then
        release the device. Idempotent."""
        if self._dev is None:
            self._state = CLOSED
            return
        if self._state != CLOSED:
            try:
                self._put(OFFLINE, "writing STATUS=offline")
            except TriggerError as exc:
                log.debug("%s: could not write STATUS=offline on close: %s", self.name, exc)
        try:
            self._usb_util.dispose_resources(self._dev)
        except self._usb_core.USBError as exc:
            log.debug("%s: releasing the device: %s", self.name, exc)
        self._state = CLOSED
