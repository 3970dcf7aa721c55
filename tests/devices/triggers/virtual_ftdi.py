"""A virtual USB bus with an emulated FTDI FT232R/FT232H, for the USB trigger tests (no hardware).

:class:`VirtualFtdi` models one chip: its descriptors, string descriptors, the vendor control requests
the station uses (reset/purge, baud rate, latency timer, bit mode, read pins), the bulk endpoints, the
kernel driver that owns a fresh FTDI on Linux, and the eight pins with the PLC wired to them.
:class:`VirtualUsbBackend` is a pyusb backend (``usb.core.find(backend=...)``) that serves such chips.
The test-side PLC drives the input pins with :meth:`VirtualFtdi.drive` and watches :meth:`VirtualFtdi.pins`
and :attr:`VirtualFtdi.history`.
"""

from __future__ import annotations

import errno
import threading
import time
from types import SimpleNamespace

import usb.backend
import usb.core

from sofast_station.devices.triggers import usbio

UART_OUTPUTS = 0x01 | 0x04 | 0x10  # TXD, RTS#, DTR#: outputs idling high in UART mode


def _gone() -> usb.core.USBError:
    return usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)


def _stall() -> usb.core.USBError:
    return usb.core.USBError("Pipe error", -9, errno.EPIPE)


class VirtualFtdi:
    """One emulated FTDI chip and the wires on its pins.

    Parameters
    ----------
    product_id : int
        0x6001 (FT232R, full speed, 64-byte packets) or 0x6014 (FT232H, high speed, 512-byte packets).
    serial : str
        Its USB serial number string.
    address : int
        Its USB address on bus 1.
    """

    def __init__(self, product_id: int = 0x6001, serial: str = "FTVIRT01", address: int = 5):
        high_speed = product_id == 0x6014
        packet = 512 if high_speed else 64
        self.product_id = product_id
        self.strings = {1: "FTDI", 2: "FT232H Single HS" if high_speed else "FT232R USB UART", 3: serial}
        self.device_descriptor = SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=64 if high_speed else 8, idVendor=0x0403, idProduct=product_id,
            bcdDevice=0x0900 if high_speed else 0x0600, iManufacturer=1, iProduct=2, iSerialNumber=3,
            bNumConfigurations=1, address=address, bus=1, port_number=address, port_numbers=(address,),
            speed=3 if high_speed else 2)
        self.config_descriptor = SimpleNamespace(
            bLength=9, bDescriptorType=2, wTotalLength=32, bNumInterfaces=1, bConfigurationValue=1,
            iConfiguration=0, bmAttributes=0x80, bMaxPower=45, extra_descriptors=[])
        self.interface_descriptor = SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0, bNumEndpoints=2,
            bInterfaceClass=0xFF, bInterfaceSubClass=0xFF, bInterfaceProtocol=0xFF, iInterface=2,
            extra_descriptors=[])
        self.endpoint_descriptors = [
            SimpleNamespace(bLength=7, bDescriptorType=5, bEndpointAddress=addr, bmAttributes=2,
                            wMaxPacketSize=packet, bInterval=0, bRefresh=0, bSynchAddress=0,
                            extra_descriptors=[])
            for addr in (usbio.EP_IN, usbio.EP_OUT)]
        self.lock = threading.RLock()
        self.plugged = True
        self.kernel_driver = True       # ftdi_sio owns a freshly plugged FTDI on Linux
        self.configuration = 0
        self.claimed: set[int] = set()
        self.bitmode = usbio.BITMODE_RESET
        self.direction = 0
        self.latch = 0
        self.latency_ms = 16
        self.baud = None
        self.external = 0xFF            # levels the PLC drives on the pins (unwired: pulled up)
        self.rx: bytearray = bytearray()
        self.requests: list[tuple[int, int, int, int]] = []   # (bmRequestType, bRequest, wValue, wIndex)
        self.history: list[tuple[float, int]] = [(time.monotonic(), self.pins())]  # pin levels over time
        self.fail_writes = False        # a stalled OUT endpoint

    # The PLC's side ------------------------------------------------------------------------------

    def pins(self) -> int:
        """The levels of D0..D7: outputs driven by the chip, inputs by the PLC."""
        with self.lock:
            if self.bitmode == usbio.BITMODE_BITBANG:
                return (self.latch & self.direction) | (self.external & ~self.direction & 0xFF)
            return UART_OUTPUTS | (self.external & ~UART_OUTPUTS & 0xFF)

    def drive(self, **levels: bool) -> None:
        """Set input pins at once, by signal name: facet_present, dump_request, recipe (0..3)."""
        bits = {"facet_present": usbio.IN_FACET_PRESENT, "dump_request": usbio.IN_DUMP_REQUEST}
        with self.lock:
            value = self.external
            for name, level in levels.items():
                if name == "recipe":
                    for bit, mask in ((1, usbio.IN_RECIPE0), (2, usbio.IN_RECIPE1)):
                        value = value | mask if level & bit else value & ~mask
                else:
                    value = value | bits[name] if level else value & ~bits[name]
            self.external = value & 0xFF

    def status(self) -> int:
        """The STATUS code on the outputs."""
        return usbio.pins_status(self.pins())

    def unplug(self) -> None:
        """Pull the cable: every later request fails with ENODEV and the bus no longer lists it."""
        with self.lock:
            self.plugged = False

    def heartbeat_toggles(self) -> int:
        """How often the HEARTBEAT pin changed level so far."""
        levels = [p & usbio.OUT_HEARTBEAT for _, p in self.history]
        return sum(a != b for a, b in zip(levels, levels[1:]))

    # The host's side (called by the backend) -----------------------------------------------------

    def _check(self) -> None:
        if not self.plugged:
            raise _gone()

    def _record(self) -> None:
        pins = self.pins()
        if pins != self.history[-1][1]:
            self.history.append((time.monotonic(), pins))

    def control(self, bm: int, req: int, value: int, index: int, data) -> int | bytes:
        with self.lock:
            self._check()
            self.requests.append((bm, req, value, index))
            if bm == 0x80 and req == 6 and value >> 8 == 3:  # GET_DESCRIPTOR(STRING)
                i = value & 0xFF
                if i == 0:
                    return bytes((4, 3, 0x09, 0x04))  # LANGID en-US
                if i not in self.strings:
                    raise _stall()
                text = self.strings[i].encode("utf-16-le")
                return bytes((2 + len(text), 3)) + text
            if bm == usbio.REQTYPE_OUT:
                if req == usbio.SIO_RESET:
                    if value in (usbio.RESET_SIO, usbio.PURGE_RX):
                        self.rx.clear()
                    return 0
                if req == usbio.SIO_SET_BAUDRATE:
                    self.baud = (value, index)
                    return 0
                if req == usbio.SIO_SET_LATENCY_TIMER:
                    if not 1 <= value <= 255:
                        raise _stall()
                    self.latency_ms = value
                    return 0
                if req == usbio.SIO_SET_BITMODE:
                    self.bitmode, self.direction = value >> 8, value & 0xFF
                    self._record()
                    return 0
            if bm == usbio.REQTYPE_IN and req == usbio.SIO_READ_PINS:
                return bytes((self.pins(),))
            raise _stall()

    def bulk_out(self, ep: int, data: bytes) -> int:
        with self.lock:
            self._check()
            if ep != usbio.EP_OUT or self.fail_writes:
                raise _stall()
            for byte in data:  # async bit-bang: each byte is clocked onto the output pins
                if self.bitmode == usbio.BITMODE_BITBANG:
                    self.latch = byte
                    self._record()
                    self.rx.append(self.pins())
            return len(data)

    def bulk_in(self, ep: int, size: int) -> bytes:
        with self.lock:
            self._check()
            if ep != usbio.EP_IN:
                raise _stall()
            n = max(0, size - 2)
            data, self.rx[:] = bytes(self.rx[:n]), self.rx[n:]
            return bytes((0x01, 0x60)) + data  # two modem-status bytes lead every packet


class VirtualUsbBackend(usb.backend.IBackend):
    """A pyusb backend whose bus holds the given :class:`VirtualFtdi` chips."""

    def __init__(self, *devices: VirtualFtdi):
        super().__init__()
        self.devices = list(devices)
        self.opened = 0

    def enumerate_devices(self):
        return [d for d in self.devices if d.plugged]

    def get_device_descriptor(self, dev):
        return dev.device_descriptor

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(config)
        return dev.config_descriptor

    def get_interface_descriptor(self, dev, intf, alt, config):
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError((intf, alt, config))
        return dev.interface_descriptor

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError((intf, alt, config))
        return dev.endpoint_descriptors[ep]

    def open_device(self, dev):
        dev._check()
        self.opened += 1
        return dev

    def close_device(self, dev_handle):
        pass

    def set_configuration(self, dev_handle, config_value):
        dev_handle._check()
        dev_handle.configuration = config_value

    def get_configuration(self, dev_handle):
        dev_handle._check()
        return dev_handle.configuration

    def claim_interface(self, dev_handle, intf):
        dev_handle._check()
        if dev_handle.kernel_driver:
            raise usb.core.USBError("Resource busy", -6, errno.EBUSY)
        dev_handle.claimed.add(intf)

    def release_interface(self, dev_handle, intf):
        dev_handle._check()
        dev_handle.claimed.discard(intf)

    def is_kernel_driver_active(self, dev_handle, intf):
        dev_handle._check()
        return dev_handle.kernel_driver

    def detach_kernel_driver(self, dev_handle, intf):
        dev_handle._check()
        dev_handle.kernel_driver = False

    def attach_kernel_driver(self, dev_handle, intf):
        dev_handle._check()
        dev_handle.kernel_driver = True

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        return dev_handle.bulk_out(ep, bytes(data))

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        data = dev_handle.bulk_in(ep, len(buff))
        buff[:len(data)] = type(buff)(buff.typecode, data)
        return len(data)

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        ret = dev_handle.control(bmRequestType, bRequest, wValue, wIndex, data)
        if bmRequestType & 0x80:  # IN: fill the buffer, return the count
            ret = bytes(ret)[:len(data)]
            data[:len(ret)] = type(data)(data.typecode, ret)
            return len(ret)
        return len(data) if data is not None else 0

    def clear_halt(self, dev_handle, ep):
        dev_handle._check()

    def reset_device(self, dev_handle):
        dev_handle._check()
