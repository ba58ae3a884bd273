"""The records of a run folder, one type per kind of line: a frame's result (a line of ``results.jsonl``),
a Monte Carlo step's (a line of ``steps.jsonl``) and the run's summary (``summary.json``).

``to_json`` gives the JSON object of the file, with the file's keys in the file's order (the fields'
order); ``from_json`` reads one back. Folders written before a key existed still read: the key takes the
value it has in a run that did not do what it records (no bank asked, nothing pruned).
"""

from dataclasses import dataclass, field, fields
from typing import Any


def _json(record: object, keep_none: bool) -> dict:
    values = {f.name: getattr(record, f.name) for f in fields(record)}
    return values if keep_none else {k: v for k, v in values.items() if v is not None}


def _known(cls: type, data: dict) -> dict:
    """``data`` checked against the fields of ``cls``: a key the type does not know is an error, not lost."""
    unknown = sorted(set(data) - {f.name for f in fields(cls)})
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown key(s) {', '.join(unknown)}")
    return data


@dataclass(kw_only=True)
class FrameResult:
    """The estimate reported for one frame (a line of ``results.jsonl``). Errors are ``None`` on a frame
    without ground truth; they are in the dataset's metric frame (degrees, metres)."""

    index: int
    """Position among the frames this run estimates."""
    frame: int
    """Position in the whole sequence (``start + index * stride``)."""
    name: str
    """The image's file name."""
    steps: int
    """Monte Carlo steps spent on the frame."""
    wall_time_s: float
    """Time of the frame's steps."""
    elapsed_s: float
    """Run time when the frame ended (all frames so far, over resumes)."""
    q: list[float]
    """The estimate as a SHIRT label: the target's attitude in the camera frame, scalar first."""
    r: list[float]
    """The target's position in the camera frame, metres."""
    c2w_model: list[list[float]]
    """The estimate as the model-frame camera-to-world matrix (OpenGL axes), 4 x 4."""
    loss: float | None
    """Loss of the estimate on the frame's ranking pixels; ``None`` on an interpolated frame."""
    outline_loss: float | None = None
    """The silhouette loss of the estimate on the frame's ranking band, unweighted: how far the model's outline
    is from the frame's (about 0.03-0.07 where the model's outline is good); ``None`` without the term."""
    silhouette_weight: float | None = None
    """The silhouette term's weight on the frame (``--optimizer.silhouette-trust`` lowers it after frames whose
    outline loss is high); ``None`` without the term."""
    candidates: int
    """Candidates of the frame's last step (0 on an interpolated frame)."""
    dropped: int
    """Candidates the last step dropped for a non-finite pose, loss or gradient."""
    object_found: bool = True
    """False when no object was found in the frame (the estimate is the prediction kept)."""
    reinitialized: bool = False
    """The bank was asked again because the object was lost."""
    bank_added: int = 0
    """Bank hypotheses that joined the frame's candidates."""
    interpolated: bool = False
    """The realtime clock skipped the frame: its pose is interpolated on SE(3) between the estimates of the
    frames before and after it, and no step looked at it."""
    observed_s: float | None = None
    """When the frame was observed on the run's clock (seconds after the first frame); ``None`` when the
    sequence has no timestamps."""
    estimated_s: float | None = None
    """When its estimate was ready on the run's clock (an interpolated frame: when the later estimate was)."""
    latency_s: float | None = None
    """``estimated_s - observed_s``: how long after it was observed the frame's pose was known."""
    rotation_deg: float | None = None
    translation_m: float | None = None
    translation_rel: float | None = None
    """Translation error over the true range."""
    score: float | None = None
    """SPEC2021 score: rotation error in radians plus ``translation_rel``."""

    def to_json(self) -> dict:
        return _json(self, keep_none=True)  # errors are written as null without ground truth

    @classmethod
    def from_json(cls, data: dict) -> "FrameResult":
        return cls(**_known(cls, data))


@dataclass(kw_only=True)
class StepRow:
    """One Monte Carlo step (a line of ``steps.jsonl``): what it started from, kept and dropped, and its
    best loss (and error, with ground truth) at every iteration."""

    index: int
    """Position among the frames this run estimates of the frame the step looked at."""
    frame: int
    """Position of that frame in the whole sequence."""
    step: int
    """Position of the step in the run."""
    wall_time_s: float
    candidates: int
    """Candidates the step started from."""
    kept: int
    """Candidates kept for the next step."""
    dropped: list[int]
    """Candidates dropped for a non-finite pose, loss or gradient."""
    pruned: list[int] = field(default_factory=list)
    """Candidates stopped early for a loss far above the best."""
    iterations: int
    """Gradient iterations run (fewer than set when the step stopped early)."""
    loss: float
    """Loss of the step's estimate on the frame's ranking pixels."""
    reinitialized: bool = False
    """The bank was asked again before this step because the object was lost."""
    bank_added: int = 0
    """Bank hypotheses that joined the candidates before this step."""
    best_loss_per_iteration: list[float]
    clock_start_s: float | None = None
    """The run's clock when the step began (seconds after the first frame was observed)."""
    clock_end_s: float | None = None
    """The run's clock when it ended: a resumed run continues from the last step's."""
    best_error_deg_per_iteration: list[float] | None = None
    """The lowest rotation error among the candidates at every iteration; ``None`` without ground truth."""
    error_of_best_loss_per_iteration: list[float] | None = None
    """The rotation error of the lowest-loss candidate at every iteration; ``None`` without ground truth."""

    def to_json(self) -> dict:
        return _json(self, keep_none=False)  # the error histories are left out without ground truth

    @classmethod
    def from_json(cls, data: dict) -> "StepRow":
        data = _known(cls, data)
        return cls(**{"iterations": len(data.get("best_loss_per_iteration", ())), **data})


@dataclass(frozen=True, kw_only=True)
class ErrorStatistics:
    """The same four numbers for every error: the typical one, the worst, and where the run ended."""

    mean: float
    median: float
    max: float
    final: float

    def to_json(self) -> dict:
        return _json(self, keep_none=True)

    @classmethod
    def from_json(cls, data: dict) -> "ErrorStatistics":
        return cls(**_known(cls, data))


@dataclass(frozen=True, kw_only=True)
class BankSummary:
    """The view bank a run started from."""

    views: int
    """Viewing directions asked for."""
    entries: int
    """Views the bank holds."""
    built_in_this_run: bool
    render_s: float
    """Time it took to render, in the run that built it."""
    cache: str
    """Where it is cached."""

    def to_json(self) -> dict:
        return _json(self, keep_none=True)

    @classmethod
    def from_json(cls, data: dict) -> "BankSummary":
        return cls(**_known(cls, data))


STATISTICS = ("rotation_deg", "translation_m", "translation_rel", "score")
"""The error fields of :class:`RunSummary` and :class:`Accuracy`, each an :class:`ErrorStatistics`."""


@dataclass(frozen=True, kw_only=True)
class Accuracy:
    """Errors and success rates over some of a run's frames with ground truth (the estimated ones alone, in
    :attr:`RunSummary.estimated_only`)."""

    frames: int
    rotation_deg: ErrorStatistics
    translation_m: ErrorStatistics
    translation_rel: ErrorStatistics
    score: ErrorStatistics
    success_rotation: dict[str, float]
    success_translation: dict[str, float]

    def to_json(self) -> dict:
        return {k: v.to_json() if isinstance(v, ErrorStatistics) else v for k, v in _json(self, True).items()}

    @classmethod
    def from_json(cls, data: dict) -> "Accuracy":
        values: dict[str, Any] = dict(_known(cls, data))
        for key in STATISTICS:
            values[key] = ErrorStatistics.from_json(values[key])
        return cls(**values)


@dataclass(kw_only=True)
class RunSummary:
    """``summary.json``: about the run (where, what model and sequence, how far it got) and the numbers over
    its frames (:func:`nerfinv_plugin.results.summary.summarize`). A field that is ``None`` is not in the
    file: the run did not record it (an older run), it does not apply (no bank, no frame yet), or the
    frames have no ground truth (the errors and success rates)."""

    run: str | None = None
    """The run folder."""
    model: str | None = None
    """The trained model's config.yml."""
    model_step: int | None = None
    sequence: str | None = None
    sequence_format: str | None = None
    frames_total: int | None = None
    """Frames the run estimates when it ends."""
    complete: bool | None = None
    device: str | None = None
    starts: str | None = None
    """Where the starting poses came from (``--starts.source``)."""
    frames_without_object: int | None = None
    frames_reinitialized: int | None = None
    target_radius_m: float | None = None
    """Radius of the sphere rays were bounded to, dataset metres."""
    bank: BankSummary | None = None
    frames_done: int
    wall_time_s: float | None = None
    """Time of all frames done."""
    mean_time_per_frame_s: float | None = None
    final_loss: float | None = None
    frames_with_truth: int | None = None
    rotation_deg: ErrorStatistics | None = None
    translation_m: ErrorStatistics | None = None
    translation_rel: ErrorStatistics | None = None
    score: ErrorStatistics | None = None
    success_rotation: dict[str, float] | None = None
    """Share of the frames with ground truth under each rotation threshold, by
    :func:`~nerfinv_plugin.results.summary.rotation_key`."""
    success_translation: dict[str, float] | None = None
    """The same under each relative translation threshold, by
    :func:`~nerfinv_plugin.results.summary.translation_key`."""
    clock: str | None = None
    """``--clock``: ``frames`` (every frame in turn) or ``realtime`` (the newest frame at every step)."""
    frames_estimated: int | None = None
    """Frames a step looked at; the others were skipped by the realtime clock and interpolated."""
    frames_skipped: int | None = None
    clock_end_s: float | None = None
    """The run's clock when the last frame done was estimated (seconds after the first was observed)."""
    latency_s: ErrorStatistics | None = None
    """Latency (observation to estimate) of the estimated frames; ``None`` without timestamps."""
    time_to_first_lock_s: float | None = None
    """The run's clock when the first estimate under
    :data:`~nerfinv_plugin.results.summary.LOCK_DEG` was ready (ground truth needed); ``None``: never."""
    first_lock_frame: int | None = None
    """That frame's position in the sequence."""
    estimated_only: Accuracy | None = None
    """The errors and success rates over the estimated frames alone, when some frames were interpolated
    (the fields above count every frame, interpolated ones included)."""

    def to_json(self) -> dict:
        return {k: v.to_json() if isinstance(v, (ErrorStatistics, BankSummary, Accuracy)) else v
                for k, v in _json(self, keep_none=False).items()}

    @classmethod
    def from_json(cls, data: dict) -> "RunSummary":
        values: dict[str, Any] = dict(_known(cls, data))
        for key in (*STATISTICS, "latency_s"):
            if values.get(key) is not None:
                values[key] = ErrorStatistics.from_json(values[key])
        if values.get("estimated_only") is not None:
            values["estimated_only"] = Accuracy.from_json(values["estimated_only"])
        if values.get("bank") is not None:
            values["bank"] = BankSummary.from_json(values["bank"])
        return cls(**values)

    def updated(self, newer: "RunSummary") -> "RunSummary":
        """This summary with every field that ``newer`` has; the fields ``newer`` lacks are kept."""
        return RunSummary.from_json(self.to_json() | newer.to_json())
