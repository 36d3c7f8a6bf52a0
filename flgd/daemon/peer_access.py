"""The daemon reads a file for a client only if that client could read it itself.

Why: the daemon may run with more rights than the member of the control group
who asks it to load ``/etc/shadow`` or another account's file.  Its reply
would then tell them something about a file they may not read (a policy
loader's "header length N does not fit the M-byte file" gives away the size
and the first bytes).  So before a command reads a path argument, the
caller's own uid and groups are checked against the mode bits of the file and
of every directory on the way to it, and a file they may not read is refused
with a message naming the problem, never the content.

The check reads the classic mode bits (owner, group, other); POSIX ACLs are
not consulted, so a file readable to the caller only through an ACL is
refused (the message says what to do).  Root and the daemon's own uid are not
checked: they read the file as the daemon does.
"""

from __future__ import annotations

import os
import pwd
import stat
from pathlib import Path

from flgd.daemon.protocol import Request

__all__ = ["FILE_ARGS_READ_FOR_CALLER", "caller_groups", "unreadable_reason", "unreadable_path_arg"]

# command -> the args naming a file the daemon reads on the caller's behalf
FILE_ARGS_READ_FOR_CALLER: dict[str, tuple[str, ...]] = {
    "policy_load": ("path",),
}


def caller_groups(uid: int, gid: int) -> set[int]:
    """The caller's primary gid (from SO_PEERCRED) and the groups its account is a member of."""
    groups = {gid}
    try:
        user = pwd.getpwuid(uid)
    except KeyError:
        return groups
    groups.add(user.pw_gid)
    try:
        groups.update(os.getgrouplist(user.pw_name, user.pw_gid))
    except OSError:
        pass
    return groups


def _allowed(st: os.stat_result, uid: int, groups: set[int], want: int) -> bool:
    """``want`` is 4 (read) or 1 (search); the owner's, group's or others' bits apply, whichever matches first."""
    if st.st_uid == uid:
        bits = (st.st_mode >> 6) & 7
    elif st.st_gid in groups:
        bits = (st.st_mode >> 3) & 7
    else:
        bits = st.st_mode & 7
    return bool(bits & want)


def _directories(path: Path) -> list[Path]:
    """Every directory from / down to the file's own, in order."""
    return list(reversed(path.parents))


def unreadable_reason(path: str | os.PathLike[str], uid: int, groups: set[int]) -> str | None:
    """Why ``uid`` (with ``groups``) could not open ``path`` for reading, or None if it could.

    A path that does not exist where the caller may look is None: the loader then says "not found",
    which the caller could have found out alone.  Both the path as given and the file a symbolic link
    leads to must be reachable and readable.
    """
    given = Path(os.path.abspath(path))
    real = Path(os.path.realpath(given))
    for target in dict.fromkeys((given, real)):
        for directory in _directories(target):
            try:
                st = os.stat(directory)
            except OSError:
                return None
            if not stat.S_ISDIR(st.st_mode):
                return None
            if not _allowed(st, uid, groups, 1):
                return f"uid {uid} may not enter the directory {directory}"
    try:
        st = os.stat(real)
    except OSError:
        return None
    if not _allowed(st, uid, groups, 4):
        return f"uid {uid} may not read it (owner uid {st.st_uid}, group {st.st_gid}, mode {stat.S_IMODE(st.st_mode):o})"
    return None


def unreadable_path_arg(request: Request, uid: int, gid: int, *, own_uid: int) -> str | None:
    """The refusal message for a request naming a file its caller may not read, or None."""
    names = FILE_ARGS_READ_FOR_CALLER.get(request.cmd, ())
    if not names or uid in (0, own_uid):
        return None
    groups: set[int] | None = None
    for name in names:
        value = request.args.get(name)
        if not isinstance(value, str):
            continue
        groups = caller_groups(uid, gid) if groups is None else groups
        why = unreadable_reason(value, uid, groups)
        if why:
            return (f"{request.cmd}: {value}: permission denied: {why}; flgd reads a file for a client only if "
                    "that client may read it itself (file mode bits; ACLs are not consulted): make the file "
                    "readable to you, or copy it somewhere you and flgd can both read")
    return None
