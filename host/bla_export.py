"""``fftune export --bla DIR``: the BLA of a session's detect step, replayed from its
captures, as one ``.mat`` per excitation level (:mod:`fftune.analysis.frf_export`: MATLAB
frd/idfrd, FdiTools and plain variables with the variances)."""
import os

from fftune.analysis.errors import FftuneError


def export_bla(source, to_dir=None):
    """Files written: ``<to_dir>/bla-L<level>.mat`` for each detect level of the captures
    in ``source`` (an output directory or its captures folder; default ``to_dir``: the
    output directory). Never overwrites."""
    from fftune.analysis.frf_export import export_bla_mat
    from fftune.host import experiments as ex
    from fftune.host import fleet

    if not os.path.isdir(source):
        raise FftuneError(f"{source}: no such directory (export --bla takes an output directory "
                          f"with captures)")
    folder = fleet._capture_dir_of(source)
    if folder is None:
        raise FftuneError(f"{source}: no capture files (captures/*.h5, *.stats.json)")
    files = fleet._capture_files(folder)
    modes = fleet._steps_on_disk(files)
    if "detect" not in modes:
        raise FftuneError(f"{source}: no detect captures (detect-*.h5): the BLA comes from the "
                          f"detect step's multisines")
    meta, problems = fleet._first_meta(files)
    if meta is None:
        raise FftuneError(f"{source}: no readable capture ({'; '.join(problems[:2])})")
    cfg = dict(meta.get("metadata", {}).get("config") or {})
    if not cfg:
        raise FftuneError(f"{source}: the captures hold no configuration (metadata.config)")
    cfg["detect"] = dict(cfg.get("detect") or {}, capture=modes["detect"])
    cfg["_source"] = os.path.join(folder, os.path.basename(files[0]))
    out_dir = os.path.dirname(folder) if os.path.basename(folder) == "captures" else folder
    session = ex.Session(fleet.CaptureReplay(meta, None), cfg, out_dir, log=lambda s: None)
    results, levels = ex.detect(session)
    if levels is None or not getattr(levels, "results", None):
        raise FftuneError(f"{source}: the detect step gave no BLA")
    unit_in = "rad" if cfg["detect"].get("inject") == "reference" else "V"
    to = to_dir or out_dir
    os.makedirs(to, exist_ok=True)
    written = []
    for i, (res, rms) in enumerate(zip(levels.results, levels.rms)):
        path = os.path.join(to, f"bla-L{i + 1:02d}.mat")
        try:
            export_bla_mat(res, path, input_unit=unit_in, output_unit="rad",
                           description=f"BLA of {source} at {rms:.4g} {unit_in} rms "
                                       f"(level {i + 1} of {len(levels.rms)}), "
                                       f"{cfg['detect'].get('inject')} -> motor angle")
        except FileExistsError:
            raise FftuneError(f"{path}: exists; exports are never overwritten") from None
        written.append(path)
    return written
