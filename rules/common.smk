# Helpers shared by the stage modules (config validation, session lookup, target lists).
import os
from pathlib import Path

from snakemake.utils import validate

from rigbuild.errors import InputError
from rigbuild.session import read_session, session_from_dict
from rigbuild.synth.session import plan_session, planned_files

validate(config, schema="../workflow/schemas/config.schema.json")
config.setdefault("characters", {})
config.setdefault("params", {})
for _stage in ("calibrate", "reconstruct", "track", "personalize", "retarget", "report"):
    config["params"].setdefault(_stage, {})

# run_sessions (optional): which of the configured sessions this run builds (default: all of them);
# lets `--configfile config/ict.yaml` run the ICT tier alone although config/config.yaml is loaded first.
SESSIONS = list(config.get("run_sessions") or config["sessions"])
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


def session_spec(session):
    """The session's SessionSpec: read from session.yaml, or planned from the synthetic block before
    the session is generated (so the DAG is known up front)."""
    folder = session_dir(session)
    if (folder / "session.yaml").exists() or not is_synthetic(session):
        return read_session(folder)
    return session_from_dict(plan_session(session, config["sessions"][session]["synthetic"]), folder,
                             source=f"config: sessions.{session}.synthetic")


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
    """Files the synth rule writes for a synthetic session (absolute paths); [] for real sessions."""
    if not is_synthetic(session):
        return []
    folder = session_dir(session)
    return [str(folder / f) for f in planned_files(session, config["sessions"][session]["synthetic"])]


def calib_images(session):
    """Calibration images: planned ones for synthetic sessions, the folder's for real ones."""
    spec = session_spec(session)
    if is_synthetic(session):
        return [f for f in synthetic_files(session) if "/calib/" in f]
    return [str(p) for cam in spec.cameras for p in spec.calib_images(cam)]


def rom_images(session, sequence):
    """ROM images of one sequence (every frame x every camera)."""
    spec = session_spec(session)
    seq = spec.sequence(sequence)
    return [str(spec.rom_image(sequence, cam, f)) for f in seq.frames for cam in spec.cameras]


def ground_truth_file(session, relpath):
    """A synthetic session's ground-truth file (for rigbuild.eval rules only; stages never read it)."""
    return str(session_dir(session) / "ground_truth" / relpath)


def performance_file(session, performance):
    return str(session_spec(session).performance_path(performance))


def sequences(session):
    return [s.name for s in session_spec(session).rom]


def performances(session):
    return [p.name for p in session_spec(session).performances]


#: retargeting methods run per (performance, character): Ribera 2017 as written, its activation-aware and
#: fitted E_Match options, the RBF-transfer and deformation-transfer baselines, and Seol 2012 spacetime cloning
RETARGET_METHODS = ["ribera", "ribera_activation", "ribera_fit", "rbf", "deformation", "seol"]


def stage_targets(session):
    """Every stage output of a session (the report depends on them all)."""
    targets = [results(session, "calib", "cameras.json")]
    targets += [results(session, "reconstruct", seq, "recon_metrics.json") for seq in sequences(session)]
    targets += [results(session, "track", "track_summary.json"), results(session, "personalize", "rig.npz")]
    for perf in performances(session):
        for character in CHARACTERS:
            for method in RETARGET_METHODS:
                targets.append(results(session, "retarget", method, perf, character, "weights.csv"))
                if is_synthetic(session):
                    targets.append(results(session, "retarget", method, perf, character, "eval_metrics.json"))
    return targets


# ---- used by rules/track.smk

def _track_images(session, seq_name, frames):
    spec = session_spec(session)
    return [str(spec.rom_image(seq_name, cam, f)) for cam in spec.cameras for f in frames]


def _track_neutral_inputs(wc):
    spec = session_spec(wc.session)
    seq = spec.rom[0]
    return {
        "session_yaml": f"{session_dir(wc.session)}/session.yaml",
        "cameras": f"results/{wc.session}/calib/cameras.json",
        "images": _track_images(wc.session, seq.name, [seq.neutral_frame]),
        "depth": f"results/{wc.session}/reconstruct/{seq.name}/depth/{seq.neutral_frame:06d}.npz",
    }


def _track_sequence_inputs(wc):
    spec = session_spec(wc.session)
    seq = next(s for s in spec.rom if s.name == wc.sequence)
    frames = [f for f in seq.frames if f >= seq.neutral_frame]
    anchor = spec.rom[0]
    return {
        "session_yaml": f"{session_dir(wc.session)}/session.yaml",
        "cameras": f"results/{wc.session}/calib/cameras.json",
        "neutral": f"results/{wc.session}/track/neutral.npz",
        "images": _track_images(wc.session, seq.name, frames),
        "depth": [f"results/{wc.session}/reconstruct/{seq.name}/depth/{f:06d}.npz" for f in frames],
        "anchor_depth": f"results/{wc.session}/reconstruct/{anchor.name}/depth/{anchor.neutral_frame:06d}.npz",
    }


# ---- used by rules/personalize.smk

def _personalize_template(wc):
    p = config["params"].get("personalize", {})
    spec = p.get("template_rig") or session_spec(wc.session).template_rig
    if spec in ("procedural", "ict"):
        return spec
    return str(Path(spec) if Path(spec).is_absolute() else Path(workflow.basedir) / spec)


# ---- used by rules/retarget.smk and rules/retarget_seol.smk (the actor's tracked ROM markers)

RIBERA_METHODS = ["ribera", "ribera_activation", "ribera_fit", "rbf", "deformation"]


def _ribera_training(wc):
    return [f"results/{wc.session}/track/{seq.name}/markers.npz" for seq in session_spec(wc.session).rom]


def _ribera_neutral_frames(wc):
    # tracked markers.npz rows start at each sequence's first frame
    return [int(seq.neutral_frame) - int(seq.start) for seq in session_spec(wc.session).rom]
