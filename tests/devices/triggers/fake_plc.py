"""A scripted PLC for the Modbus trigger tests: a pymodbus TCP server with the station's register map and
a PLC program that places facets, waits for the answer and acknowledges it, in a process of its own.

The PLC program talks to its own server through a loopback Modbus client (as an HMI would), which keeps
it independent of pymodbus's datastore API (that changed several times within 3.x).

``run_plc(port, script, events)`` is the process's target; it puts tuples on ``events``:

- ("listening", port)
- ("placed", {"serial", "sequence"})
- ("answer", {"serial", "sequence", "echo", "status", "verdict", "fault_code", "cycle"})
- ("acked", serial)
- ("finished", None) once every facet of the script was answered (and acknowledged if it acks).
"""

from __future__ import annotations

import asyncio
import socket
import time

from sofast_station.devices.triggers.modbus import (
    ACK,
    CYCLE,
    DUMP_REQUEST,
    FACET_PRESENT,
    FAULT_CODE,
    RECIPE_CODE,
    SEQUENCE,
    SEQUENCE_ECHO,
    SERIAL,
    STATION_REGISTERS,
    STATUS,
    STATUS_DONE,
    STATUS_FAULT,
    WARNINGS,
    STATUS_READY,
    VERDICT,
    RegisterMap,
    encode_ascii,
)

MAP = RegisterMap()
REGISTERS = 200  # the server's holding registers 0..199: both blocks of the default map


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _server_context():
    """Holding registers 0..REGISTERS-1, all 0, across pymodbus 3.x datastore APIs."""
    try:  # pymodbus >= 3.12
        from pymodbus.simulator import DataType, SimData, SimDevice

        return SimDevice(id=0, simdata=[SimData(0, count=REGISTERS, values=0, datatype=DataType.REGISTERS)])
    except ImportError:
        from pymodbus.datastore import ModbusSequentialDataBlock, ModbusServerContext

        try:
            from pymodbus.datastore import ModbusDeviceContext as Context
        except ImportError:  # pymodbus < 3.10
            from pymodbus.datastore import ModbusSlaveContext as Context
        return ModbusServerContext(Context(hr=ModbusSequentialDataBlock(0, [0] * (REGISTERS + 1))), single=True)


def plc_block(facet: dict, sequence: int, present: int = 1, ack: int = 0) -> list[int]:
    """The PLC block announcing ``facet`` ({"serial", "recipe_code", "recipe_name", "dump"})."""
    block = [0] * MAP.plc_registers
    block[FACET_PRESENT], block[ACK] = present, ack
    block[DUMP_REQUEST] = int(bool(facet.get("dump", False)))
    block[RECIPE_CODE] = int(facet.get("recipe_code", 0))
    block[SEQUENCE] = sequence
    block[SERIAL:SERIAL + MAP.serial_registers] = encode_ascii(facet["serial"], MAP.serial_registers)
    off = MAP.recipe_name_offset
    block[off:off + MAP.recipe_name_registers] = encode_ascii(facet.get("recipe_name", ""),
                                                             MAP.recipe_name_registers)
    return block


async def _program(port: int, script: dict, events) -> None:
    """The PLC program: place, wait for done/fault, acknowledge, wait for ready, clear ACK, repeat."""
    from pymodbus.client import AsyncModbusTcpClient

    client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=2)
    await client.connect()
    poll = script.get("poll_s", 0.005)
    acks = script.get("ack", True)

    async def station() -> list[int]:
        rr = await client.read_holding_registers(MAP.station_base, count=STATION_REGISTERS, device_id=1)
        return rr.registers

    async def write(block: list[int]) -> None:
        await client.write_registers(MAP.plc_base, block, device_id=1)

    for i, facet in enumerate(script.get("facets", [])):
        sequence = 1000 + i
        while (await station())[STATUS] != STATUS_READY:  # the station must be ready ...
            await asyncio.sleep(poll)
        # ... and ACK is 0 here (cleared below); serial, recipe and the flag go in one write.
        await write(plc_block(facet, sequence))
        events.put(("placed", {"serial": facet["serial"], "sequence": sequence}))
        while (st := await station())[STATUS] not in (STATUS_DONE, STATUS_FAULT):
            await asyncio.sleep(poll)
        events.put(("answer", {"serial": facet["serial"], "sequence": sequence, "echo": st[SEQUENCE_ECHO],
                               "status": st[STATUS], "verdict": st[VERDICT], "fault_code": st[FAULT_CODE],
                               "cycle": st[CYCLE], "warnings": st[WARNINGS]}))
        if not acks:
            continue  # a broken PLC: never acknowledges, keeps FACET_PRESENT up
        await asyncio.sleep(script.get("ack_delay_s", 0.0))
        await write(plc_block(facet, sequence, present=0, ack=1))  # acknowledge, take the facet away
        events.put(("acked", facet["serial"]))
        while (await station())[STATUS] in (STATUS_DONE, STATUS_FAULT):  # station back to ready
            await asyncio.sleep(poll)
        await client.write_registers(MAP.plc_base + ACK, [0], device_id=1)
    events.put(("finished", None))
    client.close()


async def _main(port: int, script: dict, events) -> None:
    from pymodbus.server import ModbusTcpServer

    server = ModbusTcpServer(_server_context(), address=("127.0.0.1", port))
    serving = asyncio.create_task(server.serve_forever())
    deadline = time.monotonic() + 10
    while True:  # listening once a loopback connect succeeds
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.close()
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.02)
    events.put(("listening", port))
    try:
        await _program(port, script, events)
    except Exception as exc:  # tell the test instead of dying silently
        events.put(("error", f"{type(exc).__name__}: {exc}"))
    await serving  # keep serving until the test kills the process


def run_plc(port: int, script: dict, events) -> None:
    """Process target: serve on 127.0.0.1:``port`` and run ``script``."""
    import logging

    logging.basicConfig(level=logging.ERROR)
    asyncio.run(_main(port, script, events))
