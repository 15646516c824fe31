"""The TMF8820 host interface as numbers: addresses, registers, bits, commands and packet sizes.

One definition of each constant, shared by the driver (:mod:`.i2c`), the emulator (:mod:`.emulator`),
the packet codec (:mod:`.packets`) and the Arduino bridge (:mod:`.serial_bridge`). Values are from
``docs/tmf8820-protocol.md`` unless a comment says otherwise. Register addresses are 8-bit; multi-byte
fields are little endian.
"""

from __future__ import annotations

#: 7-bit I2C address after power-up.
DEFAULT_ADDRESS = 0x41

# -- registers --------------------------------------------------------------------------------
APPID = 0x00            #: 0x80 bootloader, 0x03 measurement application; 0x00..0x03 = version bytes
VERSION = 0x00          #: app id, minor, patch, build (4 bytes)
CMD_STAT = 0x08         #: command / status register (application) and bootloader command buffer
MODE = 0x10             #: 0x00 = TMF8820/21 3x3 mode
ACTIVE_RANGE = 0x19     #: reads back the last range command (SHORT_RANGE or LONG_RANGE)
#: Serial number, 2 bytes (TMF882x register map SERIAL_NUMBER_0/1; not in the protocol notes). Used only
#: to key the factory calibration file to a sensor.
SERIAL_NUMBER = 0x1C
PAGE = 0x20             #: start of the config page / result and histogram packets
PAGE_END = 0xE0         #: one past the last page byte (0x20..0xDF: 192 bytes)
ENABLE = 0xE0
INT_STATUS = 0xE1       #: write 1 to clear a bit
INT_ENAB = 0xE2

# -- ENABLE bits -------------------------------------------------------------------------------
ENABLE_WAKEUP = 0x01    #: wake-up request (power on)
ENABLE_CPU_READY = 0x40

# -- interrupt bits (INT_STATUS, INT_ENAB) -------------------------------------------------------
INT_RESULT = 0x02
INT_ALT_RESULT = 0x04
INT_RAW_HISTOGRAM = 0x08
INT_COMMAND_DONE = 0x20
INT_ERROR = 0x40
INT_MEASUREMENT = INT_RESULT | INT_RAW_HISTOGRAM

# -- APPID values --------------------------------------------------------------------------------
APP_BOOTLOADER = 0x80
APP_MEASUREMENT = 0x03

# -- bootloader (commands written to CMD_STAT while APPID is the bootloader) -----------------------
BL_READ_RAM = 0x40
BL_WRITE_RAM = 0x41
BL_SET_ADDRESS = 0x43
BL_START_RAM_APP = 0x11   #: remap to RAM and start the downloaded application
BL_START_ROM_APP = 0x12   #: remap to ROM and start the ROM application
BL_STATUS_OK = 0x00
BL_MAX_CHUNK = 128        #: bytes per BL_WRITE_RAM command


def bl_checksum(data: bytes | list[int]) -> int:
    """Bootloader checksum of ``cmd, payload_len, payload...`` (or ``status, len, payload...``)."""
    return 0xFF ^ (sum(data) & 0xFF)


# -- application commands (written to CMD_STAT) ---------------------------------------------------
CMD_MEASURE = 0x10
CMD_STOP = 0xFF
CMD_WRITE_CONFIG = 0x15
CMD_LOAD_CONFIG_COMMON = 0x16
CMD_LOAD_SPAD_1 = 0x17
CMD_LOAD_SPAD_2 = 0x18
CMD_LOAD_FACTORY_CALIBRATION = 0x19
CMD_FACTORY_CALIBRATION = 0x20
CMD_SHORT_RANGE = 0x6E    #: short-range high-accuracy mode
CMD_LONG_RANGE = 0x6F

# -- application status (read from CMD_STAT) -------------------------------------------------------
STAT_OK = 0x00
STAT_ACCEPTED = 0x01      #: a started measurement
#: 0x02..0x0F are error codes; a value of 0x10 or more is a command still executing (the register
#: reads back the command byte until it is done; as ams' drivers poll it).
STAT_ERROR_MIN = 0x02
STAT_BUSY_MIN = 0x10

# -- config page (absolute register addresses while a config page is loaded) ----------------------
CFG_PERIOD_MS = 0x24          #: u16
CFG_KILO_ITERATIONS = 0x26    #: u16 (4000 = 4 million pulses)
CFG_CONFIDENCE_THRESHOLD = 0x30
CFG_SPAD_MAP_ID = 0x34        #: 1 = 3x3 normal, 29 x 29 deg
CFG_ALG_SETTING = 0x35        #: bit 2 report distances, bits 4:3 distance mode
CFG_HISTOGRAM_DUMP = 0x39     #: 0 off, 1 raw histograms, 2 electrical calibration histograms
SPAD_MAP_3X3 = 1
ALG_REPORT_DISTANCES = 0x04
HIST_DUMP_RAW = 1

# -- measurement output (read from PAGE) ------------------------------------------------------------
HEADER_SIZE = 4               #: cid_rid, tid, payload length (u16)
CID_RESULT = 0x10
CID_RAW_HISTOGRAM = 0x81
CID_HISTOGRAM_FLAG = 0x80
RESULT_SIZE = 132             #: bytes of a result frame, header included
RESULT_CHANNELS = 18          #: (confidence, distance) entries per object; 0..8 are zones 1..9 in 3x3 mode
HIST_SUBHEADER_SIZE = 3       #: packet number, payload, config id
HIST_DATA_SIZE = 128          #: one byte plane of one channel (128 bins)
HIST_PACKET_SIZE = HEADER_SIZE + HIST_SUBHEADER_SIZE + HIST_DATA_SIZE  # 135
HIST_CHANNELS = 10            #: channel 0 = reference, 1..9 = zones 1..9
HIST_PLANES = 3               #: bytes per 24-bit bin (0 least significant)
HIST_PACKETS = HIST_CHANNELS * HIST_PLANES  # 30
#: Payload bytes one 3x3 measurement with raw histograms puts on the bus (30 x 135 + 132 = 4182).
MEASUREMENT_BYTES = HIST_PACKETS * HIST_PACKET_SIZE + RESULT_SIZE
#: System ticks are in units of 0.2 us; the least significant bit flags a valid value.
TICK_SECONDS = 0.2e-6

# -- I2C bus -----------------------------------------------------------------------------------
CLOCKS_PER_BYTE = 9           #: 8 data bits + acknowledge
ERRNO_NAK = 121               #: Linux EREMOTEIO: no acknowledge
ERRNO_EIO = 5
ERRNO_TIMEOUT = 110           #: ETIMEDOUT: the adapter gave up (clock stretched / stalled bus)

# -- fault classes: what the driver counts in its statistics and the emulator injects -------------
#: nak / eio / timeout: a transfer failed (errno 121 / 5 / 110), retried; short_read: fewer bytes than
#: asked; reset: the device lost its state; checksum: a bootloader reply with a wrong checksum;
#: out_of_order / missing_packet: a measurement's histogram packets out of order / incomplete.
FAULT_KINDS = ("nak", "eio", "timeout", "short_read", "reset", "checksum", "out_of_order", "missing_packet")
