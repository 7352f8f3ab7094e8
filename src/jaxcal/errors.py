"""Exceptions that the command line turns into one clear line on stderr (exit status 2)."""


class JaxcalError(Exception):
    """Bad input a user can fix: a wrong file, a wrong shape, an unknown name.

    The message is one line and names what is wrong (a field, a file, a parameter).
    """


class DataError(JaxcalError, ValueError):
    """A dataset or result violates the data model (shape, dtype, value range, ordering)."""


class InputError(JaxcalError, ValueError):
    """A value passed in (a parameter, an option, an array's shape, a frame) that a user can fix.

    A `ValueError` too, for library callers; a plain `ValueError` from deep inside is no user error and
    the command line reports it as an internal one (exit status 1).
    """


class FormatError(JaxcalError):
    """A file is not a valid jaxcal file (missing or wrong `jaxcal_format`, newer version, bad layout)."""
