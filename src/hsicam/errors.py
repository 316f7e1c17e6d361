"""Exception types. The CLI turns every :class:`HsicamError` into one line and exit code 2."""


class HsicamError(Exception):
    """Base class for errors caused by the user's input (config, files, arguments)."""


class ConfigError(HsicamError, ValueError):
    """An invalid configuration: unknown key, wrong type, or a physically meaningless value."""


class InputError(HsicamError, ValueError):
    """An input file or array that cannot be used (format, shape, band grid, values)."""
