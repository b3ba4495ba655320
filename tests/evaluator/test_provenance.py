"""What a result records of what produced it, and how shards' records merge (docs/metrics.md,
Provenance)."""

from __future__ import annotations

import io
import subprocess
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path

import pytest

from evaluator import provenance as prov
from evaluator.evaluation import build_result, evaluate
from evaluator.job import ShardReport, result_from_logs, write_document
from evaluator.provenance import (
    differences,
    environment,
    local_provenance,
    merge,
    recorded_environment,
)
from evaluator.results import EvaluationResult, Machine, Provenance
from evaluator.runner import ShardOutcome
from evaluator.sources import LocalDirectory

from .conftest import SCRIPTED, tiny_plan

STARTED = datetime(2026, 1, 1, tzinfo=UTC)
IMAGE = "registry.example.org/alice/policy@sha256:" + "a" * 64


def provenance_on(plan_kwargs: dict[str, object] | None = None, **changes: object) -> Provenance:
    done = local_provenance(tiny_plan(**(plan_kwargs or {})), policy_image=IMAGE)
    return done.model_copy(update=changes)


def test_a_result_with_provenance_reads_back_as_it_was_written() -> None:
    plan = tiny_plan()
    result = build_result(plan, IMAGE, [], started=STARTED, provenance=provenance_on())
    again = EvaluationResult.model_validate_json(result.model_dump_json())
    assert again == result
    assert again.schema_version == "1.3"
    assert again.provenance is not None
    assert again.provenance.policy_image == IMAGE


def test_a_document_of_schema_1_1_reads_without_provenance_and_names_its_versions() -> None:
    document = build_result(tiny_plan(), "dir:/p", [], started=STARTED).model_dump(mode="json")
    document["schema_version"] = "1.1"
    document["versions"]["torch"] = "2.1.0+cu121"
    del document["provenance"]
    result = EvaluationResult.model_validate(document)
    assert result.provenance is None
    assert recorded_environment(document) == {
        "mani_skill": document["versions"]["mani_skill"],
        "sapien": document["versions"]["sapien"],
        "torch": "2.1.0",
        "suite_sha256": document["suite"]["sha256"],
    }


def test_the_provenance_names_the_plans_settings_backends_and_this_evaluator(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv(
        prov.EVALUATOR_IMAGE_ENV, "registry.example.org/evaluator@sha256:" + "b" * 64
    )
    plan = tiny_plan()
    found = local_provenance(plan, policy_image=None)
    assert found.environment.sim_backend == "physx_cpu"
    assert found.environment.render_backend == "sapien_cpu"
    assert found.environment.suite_sha256 == plan.suite.sha256
    assert found.environment.mani_skill == metadata.version("mani_skill")
    assert found.environment.numpy == metadata.version("numpy")
    assert found.environment.torch == metadata.version("torch").split("+")[0]
    assert found.suite_version == plan.suite.version
    assert found.settings.ignore_terminations is plan.ignore_terminations
    assert found.settings.max_episode_steps == {"PickCube-v1": 12, "PushCube-v1": 12}
    assert set(found.settings.control_mode) == {"PickCube-v1", "PushCube-v1"}
    assert (found.settings.action_chunk_max, found.settings.action_chunk_execute) == (1, 1)
    assert found.evaluator.image == "registry.example.org/evaluator@sha256:" + "b" * 64
    head = subprocess.run(
        ["git", "-C", str(prov.ROOT), "rev-parse", "HEAD"], capture_output=True, text=True
    )
    assert found.evaluator.commit == (head.stdout.strip() if head.returncode == 0 else None)
    assert found.machines == [prov.machine()]


def test_an_evaluation_records_its_provenance() -> None:
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=1)
    result = evaluate(plan, LocalDirectory(SCRIPTED))
    assert result.provenance is not None
    assert result.provenance.policy_image is None  # a directory is no image
    assert result.provenance.environment == environment(
        suite_sha256=plan.suite.sha256, sim_backends=["physx_cpu"]
    )


def test_shards_on_two_machines_merge_into_one_provenance_listing_both() -> None:
    one = provenance_on(machines=[Machine(cpu="AMD EPYC", gpu=None)])
    two = provenance_on(machines=[Machine(cpu="Intel Xeon", gpu=None)])
    merged = merge([one, two, one])
    assert merged.machines == [
        Machine(cpu="AMD EPYC", gpu=None),
        Machine(cpu="Intel Xeon", gpu=None),
    ]
    assert merged.shards == 3
    assert merged.shard_differences == {}
    assert merged.environment == one.environment


def test_shards_in_different_environments_record_each_shards_value_and_are_marked() -> None:
    one = provenance_on()
    other = one.environment.model_copy(update={"numpy": "1.26.4"})
    two = one.model_copy(update={"environment": other})
    merged = merge([one, two])
    assert merged.shard_differences == {"numpy": [one.environment.numpy, "1.26.4"]}
    document = {"provenance": merged.model_dump(mode="json")}
    assert differences(recorded_environment(document), one.environment) == ["numpy"]


def test_a_sharded_jobs_logs_give_the_merged_provenance_and_the_same_scores() -> None:
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=2)
    machines = [Machine(cpu="AMD EPYC", gpu=None), Machine(cpu="Intel Xeon", gpu="NVIDIA L4")]

    def log(index: int, provenance: Provenance | None) -> str:
        report = ShardReport(
            index=index,
            shards=2,
            policy=IMAGE,
            versions=prov.installed_versions(),
            provenance=provenance,
            started_at=STARTED,
            finished_at=STARTED,
            episodes=[],
        )
        out = io.StringIO()
        write_document(report, out)
        return out.getvalue()

    shards = [provenance_on(machines=[m]) for m in machines]
    merged = result_from_logs(plan, [log(0, shards[0]), log(1, shards[1])])
    assert merged.provenance == merge(shards)
    alone = build_result(plan, IMAGE, [ShardOutcome()], started=STARTED)
    assert merged.conditions == alone.conditions
    older = result_from_logs(plan, [log(0, shards[0]), log(1, None)])
    assert older.provenance is None  # one shard from an evaluator that records none


def test_an_environment_differs_only_on_fields_both_sides_know() -> None:
    current = environment(suite_sha256="c" * 64, sim_backends=["physx_cpu"])
    assert differences({"mani_skill": "3.0.0", "suite_sha256": "c" * 64}, current) == ["mani_skill"]
    assert differences({"suite_sha256": "d" * 64, "numpy": None}, current) == ["suite_sha256"]
    assert differences({}, current) == []
    gpu = environment(suite_sha256="c" * 64, sim_backends=["physx_cuda"])
    assert differences(current.model_dump(), gpu) == ["sim_backend", "render_backend"]


def test_without_the_package_installed_the_pinned_version_counts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def missing(name: str) -> str:
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(prov.metadata, "version", missing)
    assert prov.package_version("mani_skill") == "3.0.1"  # constraints.txt's pin
    assert prov.package_version("no-such-package") is None
    assert prov.manieval_version() == "0.1.0"  # pyproject.toml's


@pytest.mark.parametrize(
    ("text", "model"),
    [
        ("processor\t: 0\nmodel name\t: AMD EPYC 7B13\n", "AMD EPYC 7B13"),
        (
            "processor\t: 0\nBogoMIPS\t: 50.00\n\nModel\t: Raspberry Pi 4 Model B\n",
            "Raspberry Pi 4 Model B",
        ),
    ],
)
def test_the_cpu_model_is_read_from_cpuinfo(tmp_path: Path, text: str, model: str) -> None:
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(text)
    assert prov.cpu_model(cpuinfo) == model


def test_gpus_are_named_by_nvidia_smi_and_none_without_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))
    assert prov.gpu_names() is None
    smi = tmp_path / "nvidia-smi"
    smi.write_text("#!/bin/sh\nprintf 'NVIDIA H100 80GB HBM3\\nNVIDIA H100 80GB HBM3\\n'\n")
    smi.chmod(0o755)
    assert prov.gpu_names() == "2 x NVIDIA H100 80GB HBM3"
