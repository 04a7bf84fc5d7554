"""Farm-manager job descriptions that run a shot with the same CLI, chunk by chunk.

Every export has the same shape: the sim as one task (it is sequential; give it the GPU node),
then surface tasks over chunks of frames once the sim is done, then render tasks, each waiting
on the surface task of the same chunk. A task is ``sphshot run JOB --stage S`` over its chunk,
so it skips frames already valid, claims the ones it computes, and exits 0 only when every
frame of its chunk is valid on disk.

- ``slurm``: a bash script that submits three ``sbatch`` jobs: the sim (SIGUSR1 two minutes
  before its time limit makes it checkpoint and exit 5, and the job requeues itself), a surface
  array job (``--array=0-N``, task i = the chunk from frame START + i * CHUNK) after the sim,
  and a render array job whose task i waits on surface task i (``aftercorr``). Site options
  come from SPHSHOT_SBATCH / SPHSHOT_SBATCH_SIM as shell words.
- ``opencue``: a job spec XML (cjsl 1.14) with three layers; render depends on surface frame
  by frame (``FRAME_BY_FRAME``), surface on the whole sim layer (``LAYER_ON_LAYER``).
- ``openjd``: an Open Job Description template (jobtemplate-2023-09) with three steps and a
  ``Frame`` task parameter stepping by the chunk size; cancelation sends SIGTERM first, which
  makes the sim checkpoint. The job file and the output folder are PATH parameters, which
  workers' path-mapping rules rewrite.
"""
from __future__ import annotations

import getpass
import json
import math
import shlex
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from .cache import write_text_atomic
from .estimate import estimate
from .spec import ShotSpec
from .stages import STAGES, Stage

SUFFIX = {"slurm": "slurm.sh", "opencue": "cue.xml", "openjd": "openjd.json"}


def sphshot_command() -> list[str]:
    """How a farm node starts this same install of sphshot."""
    script = Path(sys.executable).with_name("sphshot")       # the venv's console script
    if script.exists():
        return [str(script)]
    return [sys.executable, "-m", "pipeline.cli"]


def run_args(job: Path, overrides: list[str], stage: str) -> list[str]:
    args = ["run", str(job)]
    for kv in overrides:
        args += ["--set", kv]
    return args + ["--stage", stage]


def export_job(spec: ShotSpec, job: Path, overrides: list[str], to: str, chunk: int,
               output: Path | None = None, farm: dict | None = None) -> Path:
    """`farm`: site settings from the command line -- show and service (OpenCue); cpus,
    mem_gb, time and gpus: SLURM requests, OpenJD host requirements, OpenCue cores and GPUs
    (GPUs go to the sim only). Without mem_gb each stage asks for the memory the pre-flight
    estimates for it (stage_memory_mb)."""
    out = output or spec.output_root / "farm" / f"{spec.shot.name}.{SUFFIX[to]}"
    extra = {"farm": farm or {}}
    text = {"slurm": slurm_script, "opencue": opencue_xml, "openjd": openjd_template}[to](
        spec, job, overrides, chunk, **extra)
    write_text_atomic(Path(out), text)
    if to == "slurm":
        Path(out).chmod(0o755)
    return Path(out)


def stage_memory_mb(spec: ShotSpec, farm: dict | None) -> dict[str, int]:
    """Each stage's memory request in MB: --mem for all if given, else the pre-flight's estimate
    for a task of that stage alone (pipeline/estimate.py: the render stage's VTK and Mesa, the
    sim's particles), rounded up to 256 MB, so that a farm neither kills a render task for
    overrunning its node's default nor books a sim's gigabytes for every render task."""
    if farm and farm.get("mem_gb"):
        mb = max(1, math.ceil(float(farm["mem_gb"]) * 1024))
        return {stage: mb for stage in STAGES}
    est = estimate(spec)
    return {stage: 256 * math.ceil(est.memory_for([stage]) / 2 ** 28) for stage in STAGES}


def _job_name(spec: ShotSpec) -> str:
    return f"{spec.shot.name}_v{spec.shot.version:03d}"


# ----------------------------------------------------------------------------------- SLURM
def slurm_script(spec: ShotSpec, job: Path, overrides: list[str], chunk: int, farm: dict | None = None) -> str:
    cmd = sphshot_command()
    a, b = spec.shot.frame_start, spec.shot.frame_end
    tasks = (b - a) // chunk + 1
    memory = stage_memory_mb(spec, farm)
    name = _job_name(spec)
    logs = spec.output_root / "farm" / "logs"

    def chunk_wrap(stage: str) -> str:
        """A chunk task: array index i runs the chunk starting at frame A + i * CHUNK (indices
        from 0, so a shot at frames 1001-1100 stays under SLURM's MaxArraySize)."""
        line = (shlex.join(cmd + run_args(job, overrides, stage))
                + f' --frames "$(({a} + SLURM_ARRAY_TASK_ID * {chunk}))" --chunk {chunk}')
        return shlex.quote("exec " + line)

    def sim_wrap() -> str:
        """The sim: SIGUSR1 (sent to this shell by --signal=B:USR1) is passed on to sphshot,
        which checkpoints and exits 5; the job then requeues itself, so it resumes from the
        checkpoint and the jobs that wait on it (afterok) still start once it is done."""
        line = (f"{shlex.join(cmd + run_args(job, overrides, 'sim'))} & pid=$!; "
                "trap 'kill -USR1 $pid' USR1; wait $pid; rc=$?; "
                "if [ $rc -gt 128 ]; then wait $pid; rc=$?; fi; "
                'if [ $rc -eq 5 ]; then scontrol requeue "$SLURM_JOB_ID"; fi; exit $rc')
        return shlex.quote(line)

    def submit(stage: Stage) -> str:
        """One sbatch line: the sequential sim as one requeueable task, a per-frame stage as an
        array of chunks after its upstream."""
        s = stage.name
        if stage.per_frame:
            after = "aftercorr" if STAGES[stage.upstream].per_frame else "afterok"
            opts = (f'--output="$LOGS/%x.%A_%a.log" \\\n    --array=0-{tasks - 1} '
                    f'--dependency={after}:${stage.upstream} --wrap={chunk_wrap(s)}')
        else:
            opts = (f'--output="$LOGS/%x.%j.log" \\\n    --signal=B:USR1@120 --requeue '
                    f'"${{sim_extra[@]}}" --wrap={sim_wrap()}')
        mem = shlex.quote(f"--mem={memory[s]}M")         # before the site's options, which win
        return f'{s}=$("$SBATCH" {mem} "${{common[@]}}" --job-name={name}.{s} {opts})\n{s}=${{{s}%%;*}}\n'

    submissions = "\n".join(submit(stage) for stage in STAGES.values())

    return f"""#!/usr/bin/env bash
# SLURM submission for sphshot shot {spec.shot.name} v{spec.shot.version:03d}, frames {a}-{b}
# (written by `sphshot export --to slurm --chunk {chunk}`). Run it with bash where sbatch works.
# It submits three jobs:
#   sim      one task; SIGUSR1 two minutes before the time limit makes it write a checkpoint
#            and exit 5, and the job requeues itself to resume from it (valid frames are skipped)
#   surface  an array job, task i = the {chunk} frames from {a} + i * {chunk}, after the sim
#   render   an array job; task i starts when surface task i succeeded (aftercorr)
# Site options (partition, account, time, GPUs, CPUs, memory) go in SPHSHOT_SBATCH_SIM (the sim)
# and SPHSHOT_SBATCH (every job), as shell words: quotes are honoured, e.g.
#   SPHSHOT_SBATCH_SIM='--gres=gpu:1 --time=4:00:00' SPHSHOT_SBATCH='--comment="shot {spec.shot.name}"'
set -euo pipefail
SBATCH="${{SBATCH:-sbatch}}"
LOGS={shlex.quote(str(logs))}
mkdir -p "$LOGS"
eval "site=(${{SPHSHOT_SBATCH:-}})"
eval "sim_extra=({_sim_requests(farm or {})} ${{SPHSHOT_SBATCH_SIM:-}})"
common=(--parsable {_requests(farm or {})}"${{site[@]}}")

{submissions}
echo "sphshot: submitted {name}: {", ".join(f"{s} ${s}" for s in STAGES)}"
"""


def _requests(farm: dict) -> str:
    """Every job's resource requests from the command line, as sbatch words (site options in
    SPHSHOT_SBATCH come after them and win)."""
    words = []
    if farm.get("cpus"):
        words.append(f"--cpus-per-task={int(farm['cpus'])}")
    if farm.get("time"):
        words.append(f"--time={farm['time']}")
    return "".join(shlex.quote(w) + " " for w in words)


def _sim_requests(farm: dict) -> str:
    return f"--gres=gpu:{int(farm['gpus'])}" if farm.get("gpus") else ""


def _openjd_amounts(farm: dict, memory_mb: int, gpu: bool) -> list[dict]:
    """OpenJD host requirements: the command line's, the stage's memory (GPUs for the sim only)."""
    out = []
    if farm.get("cpus"):
        out.append({"name": "amount.worker.vcpu", "min": int(farm["cpus"])})
    out.append({"name": "amount.worker.memory", "min": memory_mb})
    if gpu and farm.get("gpus"):
        out.append({"name": "amount.worker.gpu", "min": int(farm["gpus"])})
    return out


# --------------------------------------------------------------------------------- OpenCue
def opencue_xml(spec: ShotSpec, job: Path, overrides: list[str], chunk: int, farm: dict | None = None) -> str:
    farm = farm or {}
    cmd = sphshot_command()
    name = _job_name(spec)
    memory = stage_memory_mb(spec, farm)
    a, b = spec.shot.frame_start, spec.shot.frame_end
    root = ET.Element("spec")
    for tag, text in (("show", farm.get("show") or "sphshot"), ("shot", spec.shot.name), ("user", getpass.getuser())):
        ET.SubElement(root, tag).text = text
    job_el = ET.SubElement(root, "job", name=name)
    for tag, text in (("paused", "False"), ("maxretries", "2"), ("autoeat", "False")):
        ET.SubElement(job_el, tag).text = text
    layers = ET.SubElement(job_el, "layers")

    def layer(stage: str, frames: str, size: int, extra: list[str]) -> None:
        el = ET.SubElement(layers, "layer", name=stage, type="Render")
        ET.SubElement(el, "cmd").text = shlex.join(cmd + run_args(job, overrides, stage) + extra)
        ET.SubElement(el, "range").text = frames
        ET.SubElement(el, "chunk").text = str(size)
        if farm.get("cpus"):
            ET.SubElement(el, "cores").text = str(int(farm["cpus"]))
        ET.SubElement(el, "memory").text = f"{memory[stage]}m"    # cuebot reads "<n>m" as MB (a bare n: GB)
        if farm.get("gpus") and stage == "sim":
            ET.SubElement(el, "gpus").text = str(int(farm["gpus"]))
        services = ET.SubElement(el, "services")
        ET.SubElement(services, "service").text = farm.get("service") or "shell"

    chunked = ["--frames", "#FRAME_START#-#FRAME_END#"]
    for stage in STAGES.values():
        if stage.per_frame:
            layer(stage.name, f"{a}-{b}", chunk, chunked)
        else:   # the sim is one frame of its layer running the whole shot
            layer(stage.name, str(a), 1, [])
    depends = ET.SubElement(root, "depends")
    for stage in STAGES.values():
        if stage.upstream is None:
            continue
        kind = "FRAME_BY_FRAME" if STAGES[stage.upstream].per_frame else "LAYER_ON_LAYER"
        d = ET.SubElement(depends, "depend", type=kind, anyframe="False")
        for tag, text in (("depjob", name), ("deplayer", stage.name), ("onjob", name), ("onlayer", stage.upstream)):
            ET.SubElement(d, tag).text = text
    ET.indent(root)
    return ('<?xml version="1.0"?>\n'
            '<!DOCTYPE spec PUBLIC "SPI Cue Specification Language" '
            '"http://localhost:8080/spcue/dtd/cjsl-1.14.dtd">\n'
            + ET.tostring(root, encoding="unicode") + "\n")


# ---------------------------------------------------------------------------------- OpenJD
def openjd_template(spec: ShotSpec, job: Path, overrides: list[str], chunk: int, farm: dict | None = None) -> str:
    """The job file and the shot's output folder are PATH job parameters (JobFile, ShotOutput),
    so a worker's path-mapping rules (another OS, another mount point) map them; the tasks read
    them as {{Param.JobFile}} and --set shot.output='{{Param.ShotOutput}}'. OpenJD allows a
    PATH parameter no default outside the template's folder, so the submitter gives both (the
    values of this export are in their descriptions): openjd run T -p JobFile=... -p ShotOutput=..."""
    cmd = sphshot_command()
    a, b = spec.shot.frame_start, spec.shot.frame_end
    shot_output = spec.output_root.parent.parent           # <output>/<name>/v### -> <output>
    mapped = [*overrides, "shot.output='{{Param.ShotOutput}}'"]
    memory = stage_memory_mb(spec, farm)

    def action(stage: str, extra: list[str]) -> dict:
        return {"onRun": {"command": cmd[0],
                          "args": cmd[1:] + run_args(Path("{{Param.JobFile}}"), mapped, stage) + extra,
                          "cancelation": {"mode": "NOTIFY_THEN_TERMINATE", "notifyPeriodInSeconds": 120}}}

    frame_param = {"taskParameterDefinitions": [{"name": "Frame", "type": "INT", "range": f"{a}-{b}:{chunk}"}]}
    chunked = ["--frames", "{{Task.Param.Frame}}", "--chunk", str(chunk)]

    def step(stage: Stage) -> dict:
        out: dict = {"name": stage.name}
        if stage.upstream:
            out["dependencies"] = [{"dependsOn": stage.upstream}]
        if stage.per_frame:
            out["parameterSpace"] = frame_param
        out["hostRequirements"] = {"amounts": _openjd_amounts(farm or {}, memory[stage.name],
                                                              gpu=not stage.per_frame)}
        out["script"] = {"actions": action(stage.name, chunked if stage.per_frame else [])}
        return out

    template = {
        "specificationVersion": "jobtemplate-2023-09",
        "name": f"sphshot {spec.shot.name} v{spec.shot.version:03d}",
        "parameterDefinitions": [
            {"name": "JobFile", "type": "PATH", "objectType": "FILE", "dataFlow": "IN",
             "description": f"the sphshot job file (TOML); exported with {job}"},
            {"name": "ShotOutput", "type": "PATH", "objectType": "DIRECTORY", "dataFlow": "OUT",
             "description": f"shot.output, the folder the shot is written below; exported with {shot_output}"},
        ],
        "steps": [step(stage) for stage in STAGES.values()],
    }
    return json.dumps(template, indent=2) + "\n"
