"""Write files whole or not at all: a temporary file in the same directory, then rename."""
import os
import tempfile


def _umask():
    """The process's umask (read by setting it and setting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_atomic(path, data, *, overwrite=True):
    """Write ``data`` (bytes or str) to ``path`` via a temporary file and :func:`os.replace`;
    the file's mode is what :func:`open` would give it (0666 less the umask).

    With ``overwrite=False`` an existing ``path`` is never replaced (:func:`os.link` of the
    finished temporary file fails instead), and :class:`FileExistsError` is raised.
    """
    d = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix="-" + os.path.basename(path), dir=d)
    try:
        with os.fdopen(fd, "wb") as fh:
            # mkstemp makes 0600: the file gets the mode open() gives (0666 less the umask)
            os.fchmod(fh.fileno(), 0o666 & ~_umask())
            fh.write(data.encode("utf-8") if isinstance(data, str) else data)
            fh.flush()
            os.fsync(fh.fileno())
        if overwrite:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)
            os.remove(tmp)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
