"""MAVLink FTP (file transfer over MAVLink) on a :class:`~mrft_gcs.link.VehicleLink`.

pymavlink's ``mavftp.MAVFTP`` (pymavlink >= 2.4.41) reads its replies with ``recv_match`` on
the connection, but a VehicleLink's reader thread owns that connection. :class:`_LinkPort`
gives MAVFTP what it needs of a connection (send, receive, our own ids) through the link: FTP
replies arrive as :class:`~mrft_gcs.link.vehicle.FtpFrame` events, frames go out through the
link's send lock, and the tlog records both.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from mrft_gcs.errors import LinkError, MissingDependency
from mrft_gcs.link.vehicle import FtpFrame, Subscription, VehicleLink

__all__ = ["FtpEntry", "list_dir", "put_file", "remove_file"]

#: seconds one FTP operation may take (more than the idle detection below)
FTP_TIMEOUT_S = 10.0
#: MAVFTP ends a remove, or a list that failed, only after this much FTP silence (its
#: default 3.7 s made each such step take 3.7 s); an answer slower than this is a lost one
IDLE_DETECTION_S = 1.0


@dataclass(frozen=True, slots=True)
class FtpEntry:
    """One entry of a vehicle directory: ``size_b`` in bytes (0 for a directory)."""

    name: str
    is_dir: bool
    size_b: int


@dataclass(frozen=True, slots=True)
class _Frame:
    """What MAVFTP reads of a FILE_TRANSFER_PROTOCOL message (the link only passes ours)."""

    payload: bytes
    target_system: int
    target_component: int

    def get_type(self) -> str:
        return "FILE_TRANSFER_PROTOCOL"


class _LinkPort:
    """The slice of a pymavlink connection that ``MAVFTP`` uses, served by a VehicleLink."""

    def __init__(self, link: VehicleLink, sub: Subscription) -> None:
        self._link = link
        self._sub = sub
        self.mav = self  # MAVFTP sends with ``master.mav.file_transfer_protocol_send``
        self.source_system, self.source_component = link.source_ids

    def file_transfer_protocol_send(self, network: int, _system: int, _component: int,
                                    payload: Any) -> None:
        self._link.send_file_transfer(bytes(payload), network)

    def recv_match(self, type: Any = None, blocking: bool = True,  # noqa: A002 (pymavlink's)
                   timeout: float | None = None) -> _Frame | None:
        event = self._sub.get(timeout if timeout is not None else 1.0)
        if not isinstance(event, FtpFrame):
            return None
        return _Frame(event.payload, self.source_system, self.source_component)


@contextmanager
def _session(link: VehicleLink) -> Iterator[Any]:
    try:
        from pymavlink import mavftp
    except ImportError as err:  # pragma: no cover - only with a pymavlink older than 2.4.41
        raise MissingDependency("MAVLink FTP needs pymavlink >= 2.4.41 (pymavlink.mavftp): "
                                "pip install -U pymavlink") from err
    settings = mavftp.MAVFTPSettings(
        [("debug", int, 0), ("pkt_loss_tx", int, 0), ("pkt_loss_rx", int, 0),
         ("max_backlog", int, 5), ("burst_read_size", int, 80), ("write_size", int, 80),
         ("write_qsize", int, 5), ("idle_detection_time", float, IDLE_DETECTION_S),
         ("read_retry_time", float, 0.8), ("retry_time", float, 0.5)])
    with link.subscribe(FtpFrame) as sub:
        yield mavftp.MAVFTP(_LinkPort(link, sub), link.target_system, link.target_component,
                            settings=settings)


def _check(ret: Any, what: str) -> None:
    if ret.error_code != 0:
        name = getattr(ret.error_code, "name", str(ret.error_code))
        raise LinkError(f"MAVLink FTP {what} failed ({name}): check the link, and that the "
                        f"vehicle has a card or file system (SD card on a flight controller)")


def list_dir(link: VehicleLink, path: str) -> list[FtpEntry] | None:
    """Entries of the vehicle directory ``path``; None if it does not exist or cannot be read."""
    with _session(link) as ftp:
        ret = ftp.cmd_list([path])
    if ret.error_code != 0:
        return None
    return [FtpEntry(e.name, bool(e.is_dir), int(e.size_b))
            for e in (ret.directory_listing or ()) if e.name not in (".", "..")]


def put_file(link: VehicleLink, path: str, data: bytes) -> None:
    """Write ``data`` to the vehicle file ``path`` (replaced if it exists).

    Raises
    ------
    LinkError
        The vehicle refused or did not answer.
    """
    import io

    with _session(link) as ftp:
        ret = ftp.cmd_put(["upload", path], fh=io.BytesIO(data))
        _check(ret, f"create {path}")
        _check(ftp.process_ftp_reply("put", timeout=FTP_TIMEOUT_S), f"write {path}")


def remove_file(link: VehicleLink, path: str) -> bool:
    """Delete the vehicle file ``path``; False if it was not there (or could not be removed)."""
    with _session(link) as ftp:
        ret = ftp.cmd_rm([path])
    return bool(ret.error_code == 0)
