# Helpers shared by the stage modules: config validation at DAG start, session lookup, target lists.
import functools
import importlib.util
import os
from pathlib import Path

from snakemake.utils import validate

from rigbuild.errors import InputError
from rigbuild.params import STAGE_PARAMS, load_from_config
from rigbuild.retarget.methods import PIPELINE_METHODS
from rigbuild.session import read_session, session_from_dict
from rigbuild.synth.session import check_synthetic, plan_session, planned_files

validate(config, schema="../workflow/schemas/config.schema.json")


wildcard_constraints:
    session="[^/]+",

config.setdefault("characters", {})
config.setdefault("params", {})
for _stage in STAGE_PARAMS:
    config["params"].setdefault(_stage, {})


def validate_stage_params():
    """Every params.<stage> block checked against the stage's typed definition before any job runs."""
    from rigbuild.params import check_keys

    check_keys(config["params"], STAGE_PARAMS, "params")
    for stage, target in STAGE_PARAMS.items():
        if importlib.util.find_spec(target.split(":")[0]) is not None:
            load_from_config(stage)(config["params"][stage])


validate_stage_params()



def configfile_sessions():
    """Sessions named by the --configfile files (and --config) of this run: config/config.yaml is always
    loaded first, and a technician's config naming its own sessions builds only those, not the demo."""
    given = getattr(workflow.config_settings, "overwrite_config", None) or {}
    return list(given.get("sessions") or {})


# run_sessions (optional): which of the configured sessions this run builds; default: the sessions of the
# --configfile files, or every configured session when none names any (plain `snakemake`: the demo).
SESSIONS = list(config.get("run_sessions") or configfile_sessions() or config["sessions"])
_unknown_sessions = [s for s in SESSIONS if s not in config["sessions"]]
if _unknown_sessions:
    raise InputError(f"field 'run_sessions': unknown sessions {_unknown_sessions}", path="config",
                     fix=f"use names from sessions: {', '.join(config['sessions'])}")
CHARACTERS = list(config["characters"])


def session_dir(session):
    """The session folder (absolute path)."""
    p = Path(config["sessions"][session]["path"])
    return p if p.is_absolute() else Path(workflow.basedir) / p


def is_synthetic(session):
    return "synthetic" in config["sessions"][session]


@functools.lru_cache(maxsize=None)
def _session_spec(session, generated):
    folder = session_dir(session)
    if generated or not is_synthetic(session):
        return read_session(folder)
    return session_from_dict(plan_session(session, config["sessions"][session]["synthetic"]), folder,
                             source=f"config: sessions.{session}.synthetic")


def session_spec(session):
    """The session's SessionSpec: read from session.yaml, or planned from the synthetic block before
    the session is generated (so the DAG is known up front). Read once per session and state (input
    functions call it per job)."""
    return _session_spec(session, (session_dir(session) / "session.yaml").exists())


def session_yaml(session):
    return str(session_dir(session) / "session.yaml")


def check_rig_spec(spec, where):
    """Fail at DAG start when a rig spec points nowhere."""
    if spec in ("procedural", "ict"):
        if spec == "ict":
            from rigbuild.paths import ict_dir

            if not (ict_dir() / "generic_neutral_mesh.obj").exists():
                raise InputError(f"field '{where}': the ICT rig needs ICT-FaceKit at {ict_dir()}",
                                 path="config", fix="set RIGBUILD_DATA to the folder holding ict-facekit/")
        return
    p = Path(spec) if Path(spec).is_absolute() else Path(workflow.basedir) / spec
    if not p.exists():
        raise InputError(f"field '{where}': rig '{spec}' not found ({p})", path="config",
                         fix="give procedural, ict, an OBJ folder with neutral.obj or a rig .npz")


# Validate every session and rig at DAG start: errors name the file and the field.
for _s in SESSIONS:
    if is_synthetic(_s):
        check_synthetic(config["sessions"][_s]["synthetic"], f"sessions.{_s}.synthetic")
    _spec = session_spec(_s)
    check_rig_spec(_spec.template_rig, f"sessions.{_s} template_rig")
for _c, _cfg in config["characters"].items():
    check_rig_spec(_cfg["rig"], f"characters.{_c}.rig")


def check_shape_names():
    """`shapes:` (optional) restricts the template rig's shapes; every name must exist in every
    session's template rig."""
    if not config.get("shapes"):
        return
    from rigbuild.io.rigs import load_rig

    for s in SESSIONS:
        spec = session_spec(s).template_rig
        rig = load_rig(spec if spec in ("procedural", "ict") else str(Path(workflow.basedir) / spec))
        unknown = [n for n in config["shapes"] if n not in rig.shape_names]
        if unknown:
            raise InputError(f"field 'shapes': unknown shape names {unknown} for template rig '{spec}'",
                             path="config", fix=f"use names from: {', '.join(rig.shape_names)}")


check_shape_names()


def results(session, *parts):
    return str(Path("results") / session / Path(*parts)) if parts else str(Path("results") / session)


def synthetic_files(session):
    """What the synth rule declares for a synthetic session (absolute paths; [] for real sessions): session.yaml,
    the performances and ground_truth/ file by file, and the image folders calib/ and rom/ as directories."""
    if not is_synthetic(session):
        return []
    folder = session_dir(session)
    files = [f for f in planned_files(session, config["sessions"][session]["synthetic"])
             if not f.startswith(("calib/", "rom/"))]
    return [str(folder / f) for f in files] + [directory(str(folder / "calib")), directory(str(folder / "rom"))]


def capture_images(session, paths):
    """A job's image inputs: the files of a real capture; none for a synthetic session, whose images the
    generator writes with session.yaml (which every such job declares). Listing every generated image made
    Snakemake match each of them against every other output at DAG build."""
    return [] if is_synthetic(session) else [str(p) for p in paths]


def calib_images(session):
    """A real capture's calibration inputs (none listed for a synthetic session: see capture_images): the rig
    images, each camera's own intrinsics images and a session.yaml ``intrinsics:`` file."""
    if is_synthetic(session):
        return []
    spec = session_spec(session)
    files = [str(p) for cam in spec.cameras for p in spec.calib_images(cam) + spec.intrinsics_images(cam)]
    given = spec.raw.get("intrinsics")
    if isinstance(given, str):
        files.append(str(Path(given) if Path(given).is_absolute() else spec.root / given))
    return files


def ground_truth_file(session, relpath):
    """A synthetic session's ground-truth file (for rigbuild.eval rules only; stages never read it)."""
    return str(session_dir(session) / "ground_truth" / relpath)


def performance_file(session, performance):
    return str(session_spec(session).performance_path(performance))


def sequences(session):
    return [s.name for s in session_spec(session).rom]


def performances(session):
    return [p.name for p in session_spec(session).performances]


def calibration_only(session):
    """A session without ROM sequences and performances: only calibrated (and reported)."""
    return session_spec(session).calibration_only


def stage_targets(session):
    """Every stage output of a session the report shows (the metrics rule gathers the numbers)."""
    targets = [results(session, "calib", "cameras.json")]
    if calibration_only(session):
        return targets
    targets += [results(session, "reconstruct", seq, "recon_summary.json") for seq in sequences(session)]
    targets += [results(session, "track", "track_summary.json"), results(session, "personalize", "rig.npz")]
    for perf in performances(session):
        for character in CHARACTERS:
            for method in PIPELINE_METHODS:
                targets.append(results(session, "retarget", method, perf, character, "weights.csv"))
    return targets


def metric_files(session):
    """Every metrics fragment of a session, stage by stage (ground-truth evaluation for synthetic sessions)."""
    files = []
    stages = ("calibrate",) if calibration_only(session) else ("calibrate", "reconstruct", "track", "personalize",
                                                              "retarget")
    for stage in stages:
        files += globals()[f"{stage}_metric_files"](session)
        if is_synthetic(session):
            files += globals()[f"eval_{stage}_metric_files"](session)
    return files
