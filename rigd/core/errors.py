"""Error hierarchy: callers catch the narrowest class that lets them act."""


class RigdError(Exception):
    """Base of every error rigd raises on purpose."""


class ConfigError(RigdError):
    """A rig config or device spec is invalid; the message names the field."""


class DeviceError(RigdError):
    """A device failed, refused a command or could not be opened."""


class BackendUnavailableError(DeviceError):
    """The backend for a spec needs an optional library that is not installed."""


class DeviceTimeoutError(DeviceError):
    """A device did not answer within its deadline."""


class ProtocolError(DeviceError):
    """A device answered with an error reply or bytes that break its protocol."""


class EventDataError(RigdError):
    """Event arrays with wrong dtypes, lengths or values."""


class SyncError(RigdError):
    """Device clocks could not be mapped to the rig timebase."""


class TakeError(RigdError):
    """A take could not be written or read."""


class TakeFormatError(TakeError):
    """A take file violates the schema; the message names the HDF5 path."""


class NotATakeError(TakeFormatError):
    """An HDF5 file that is not a rigd take (another schema): skipped, not repaired."""


class TakeInUseError(TakeError):
    """The take is open for writing in another process (HDF5 file lock); leave it alone."""


class TakeTruncatedError(TakeFormatError):
    """A write failed (disk full, file size limit) after HDF5 had recorded a longer file:
    the file ends at `eof`, its superblock says `stored_eof`, and HDF5 refuses to open it."""

    def __init__(self, message: str, eof: int, stored_eof: int) -> None:
        super().__init__(message)
        self.eof = eof
        self.stored_eof = stored_eof


class WriteDeferredError(OSError):
    """The file system refused a write of data the take had already taken in (disk full): the
    take holds that data and writes it when it is failed or closed, in the room the ballast
    makes. An OSError like any refused write (the take stops), but the data is not a loss."""


class MissingExtraError(RigdError):
    """A feature needs a library that `pip install rigd` leaves out (an extra: rigd[capture], ...)."""
