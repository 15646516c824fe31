"""The TMF8820 time-of-flight sensor: register map, packet codec, I2C driver, register-level emulator,
Intel HEX RAM patch and the Arduino serial bridge. Heavy or optional packages (smbus2, pyserial,
intelhex, gpiod) are imported where they are used.
"""
