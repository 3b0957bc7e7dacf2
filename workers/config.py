"""The job config: one pydantic schema from the API request down to the training loop.

A job names a method and a size profile (model/profiles.py) and may override any profile field with
a dotted key (`occupancy.steps=200`, `network.width=128`); the resolved profile is what the loop
trains."""

from __future__ import annotations

import json
import types
from functools import lru_cache
from typing import TYPE_CHECKING, Any, Literal, Union, get_args, get_origin

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    StrictInt,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from model.methods import METHODS, get_method
from model.methods.spec import setting
from model.profiles import MAX_STEPS, PROFILES, Profile, upgrade_saved

if TYPE_CHECKING:
    from model.methods.base import Method

MAX_WORKERS = 8
# The smoke profile checks that a pipeline runs end to end in seconds; one 32-step fit took 5.4 s
# against 2.0 s for all 20 training steps of a smoke run on the tiny city (profiled under load).
SMOKE_APPEARANCE_STEPS = 4


class TrainConfig(BaseModel):
    # Bounded on both sides and finite, like the profile it overrides.
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    # Validated against the registry (model/methods/registry.py) when the config is made, so a
    # method registered later (a plug-in, a test's toy method) is accepted; the enum tells API
    # clients the built-in ones.
    method: str = Field(
        json_schema_extra={"enum": list(METHODS)},
        max_length=64,
        description="the method to train (GET /v1/methods lists them)",
    )
    profile: str = Field(
        "cpu",
        json_schema_extra={"enum": list(PROFILES)},
        description="the size profile whose settings the run starts from (docs/PROFILES.md)",
    )
    overrides: dict[str, Any] = Field(
        default_factory=dict,
        description='profile settings by dotted key, e.g. {"occupancy.steps": 200} '
        "(`leco settings` lists them)",
    )
    workers: StrictInt = Field(
        1,
        ge=1,
        le=MAX_WORKERS,
        description="data-parallel workers, each with its share of the rays",
    )
    use_gpu: bool = Field(False, description="one GPU per worker (CUDA)")
    budget_min: float | None = Field(
        None,
        gt=0,
        le=7 * 24 * 60,
        description="wall-clock budget for the whole run (both phases), in minutes; None: the "
        "profile's steps",
    )
    seed: StrictInt = Field(0, ge=0, le=2**31 - 1, description="seeds weights, rays and samples")
    downscale: StrictInt | None = Field(
        None,
        ge=1,
        le=64,
        description="integer factor applied to images and intrinsics for training and evaluation "
        "alike (None: the scene's own scale; for LLFF its smallest images_N folder); the paper "
        "uses 4 on Mega-NeRF scenes",
    )
    checkpoint_every: StrictInt = Field(
        200, ge=1, le=MAX_STEPS, description="steps between checkpoints (a restart resumes there)"
    )
    metrics_every: StrictInt = Field(
        10, ge=1, le=MAX_STEPS, description="steps between rows of the metrics log"
    )
    val_every: StrictInt | None = Field(
        None,
        ge=10,
        le=MAX_STEPS,
        description="steps between validation renders (None: only at the end)",
    )
    eval_every_s: float | None = Field(
        None,
        gt=0,
        le=86_400,
        description="validation PSNR/SSIM (and occupancy metrics while one is learned) every this "
        "many seconds of training time and at each phase's end; not counted as training time",
    )
    eval_views: StrictInt = Field(
        4, ge=1, le=1000, description="validation views each periodic evaluation renders"
    )
    val_appearance_steps: StrictInt = Field(
        32,
        ge=0,
        le=1000,
        description="validation protocol: right halves scored, appearance embeddings fitted on the "
        "left halves for this many steps with the networks frozen (0: the training embeddings' "
        f"mean); {SMOKE_APPEARANCE_STEPS} when not given at the smoke profile",
    )
    max_failures: StrictInt = Field(
        3,
        ge=0,
        le=100,
        description="worker-group restarts Ray Train may make from the last checkpoint",
    )
    pixels_on_device_max_mb: float = Field(
        4096,
        ge=0,
        le=1_048_576,
        description="a GPU worker holds its split's pixels on the device (7 bytes a pixel: colour "
        "and place in the epoch's order) up to this many MB, so a ray batch is made there without "
        "a copy; a larger split is drawn on the host ahead of the step and copied without a wait",
    )
    compile: bool = Field(
        False,
        description="torch.compile (inductor) the networks each phase trains (fields and their "
        "encodings, proposal networks; LeCO's phase 1 is not compiled); the compiling counts as "
        "training time (a CPU worker needs a C++ compiler)",
    )
    max_nonfinite_steps: StrictInt = Field(
        20,
        ge=1,
        le=10_000,
        description="consecutive skipped (non-finite) steps before the run fails",
    )
    # The profile a run trained with, once it has one (`pinned`): not part of the job's config.
    _pinned: Profile | None = PrivateAttr(None)

    @field_validator("method")
    @classmethod
    def known_method(cls, name: str) -> str:
        get_method(name)  # raises naming the registered methods
        return name

    @field_validator("profile")
    @classmethod
    def known_profile(cls, name: str) -> str:
        if name not in PROFILES:
            raise ValueError(f"unknown profile {name!r}: choose one of {', '.join(PROFILES)}")
        return name

    @model_validator(mode="before")
    @classmethod
    def smoke_fits_briefly(cls, data: Any) -> Any:
        if (
            isinstance(data, dict)
            and data.get("profile") == "smoke"
            and "val_appearance_steps" not in data
        ):
            return {**data, "val_appearance_steps": SMOKE_APPEARANCE_STEPS}
        return data

    @model_validator(mode="after")
    def overrides_resolve(self) -> "TrainConfig":
        self.resolved_profile()  # raises with the offending key named
        return self

    def pinned(self, profile: Profile | dict) -> "TrainConfig":
        """This job resolved to the profile its run trained with (saved in run.json, checkpoints
        and final/models.pt), so a later change of a profile's defaults does not reach a run made
        before it, when it resumes or is loaded to render."""
        try:
            saved = upgrade_saved(profile) if isinstance(profile, dict) else profile
            fixed = Profile.model_validate(saved)
        except ValidationError as error:
            raise ValueError(
                "the run was trained with settings this version cannot read "
                f"({error.error_count()} problems, first: {error.errors()[0]['msg']} at "
                f"{'.'.join(map(str, error.errors()[0]['loc']))}); train it again"
            ) from None
        copy = self.model_copy()
        copy._pinned = fixed
        return copy

    def resolved_profile(self) -> Profile:
        if self._pinned is not None:
            return self._pinned
        spec = get_method(self.method)
        data = PROFILES[self.profile].model_dump()
        for key, value in self.overrides.items():
            section = spec.shared_key(key)
            if section is not None:
                raise ValueError(
                    f"override {key!r}: {self.method} reads {key.split('.')[0]} from its own "
                    f"section, {section}; set {spec.own_key(key)!r} instead"
                )
            node, name = setting_node(data, key)
            node[name] = strict_value(key, value)
        try:
            profile = Profile.model_validate(data)
        except ValidationError as error:
            problems = "; ".join(
                f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in error.errors()
            )
            raise ValueError(f"overrides make an invalid profile: {problems}") from None
        # the method's own sections in place of the shared ones its code reads (MethodSpec.sections)
        sections = {shared: setting(profile, own) for shared, own in spec.sections}
        return profile.model_copy(update=sections) if sections else profile

    @property
    def global_batch(self) -> int:
        return self.resolved_profile().rays_per_device * self.workers

    def method_for_run(self) -> Method:
        """The method of this job, made from its resolved profile (model/methods)."""
        return get_method(self.method)(self.resolved_profile())

    @property
    def phases(self) -> tuple[str, ...]:
        return get_method(self.method).phases

    def phase_steps(self, phase: str) -> int:
        return get_method(self.method).steps(self.resolved_profile(), phase)


def setting_node(data: dict, key: str) -> tuple[dict, str]:
    """The section of a dumped profile that holds the dotted key, and the key's last part."""
    node, parts = data, key.split(".")
    for part in parts[:-1]:
        if not isinstance(node.get(part), dict):
            raise ValueError(f"override {key!r}: {part!r} is not a section of the profile")
        node = node[part]
    if parts[-1] not in node or isinstance(node[parts[-1]], dict):
        raise ValueError(f"override {key!r}: no such setting in the profile{near(key)}")
    return node, parts[-1]


def strict_value(key: str, value: Any) -> Any:
    """An override's value checked against its setting's type without coercion, as the API's own
    fields are (StrictInt): lax parsing read `true` or `"2"` as the integer 1 or 2. An integer is a
    number too; a list stands for a tuple (JSON has no tuples). The profile checks the bounds."""
    annotation = setting_annotation(key)
    try:
        return adapter(annotation).validate_python(
            tuple(value) if isinstance(value, list) else value, strict=True
        )
    except ValidationError:
        raise ValueError(
            f"override {key!r}: expected {expected(annotation)}, got {described(value)}"
        ) from None


def setting_annotation(key: str) -> Any:
    """The type of the profile setting at a dotted key (setting_node has checked it is one)."""
    annotation: Any = Profile
    for part in key.split("."):  # each part but the last names a section: a model
        annotation = annotation.model_fields[part].annotation
    return annotation


@lru_cache(maxsize=None)
def adapter(annotation: Any) -> TypeAdapter:
    return TypeAdapter(annotation)


def expected(annotation: Any) -> str:
    """What a setting of this type takes, in JSON's words."""
    args = get_args(annotation)
    if get_origin(annotation) in (Union, types.UnionType):
        return " or ".join(expected(a) for a in args if a is not type(None)) + " or null"
    if get_origin(annotation) is Literal:
        return "one of " + ", ".join(json.dumps(a) for a in args)
    if get_origin(annotation) is tuple:
        return "a list of " + {int: "integers", float: "numbers"}.get(args[0], "values")
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    return names.get(annotation, str(annotation))


def described(value: Any) -> str:
    """A client's value by its JSON type, and itself where short (error details stay bounded)."""
    if value is None:
        return "null"
    kinds = {bool: "a boolean", int: "an integer", float: "a decimal number", str: "a string"}
    kind = {**kinds, list: "a list", tuple: "a list", dict: "an object"}.get(type(value), "a value")
    try:
        shown = json.dumps(value)
    except (TypeError, ValueError):  # not JSON (a Python caller's object)
        return kind
    return f"{kind} ({shown})" if len(shown) <= 40 else kind


def near(key: str) -> str:
    """A hint naming the settings closest to a mistyped key (`leco settings` lists them all)."""
    from difflib import get_close_matches

    from model.profiles import settings

    keys = [k for k, _, _ in settings(PROFILES["cpu"])]
    close = get_close_matches(key, keys, n=3, cutoff=0.85)
    return f" (did you mean {' or '.join(close)}?)" if close else " (`leco settings` lists them)"


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """`key=value` strings (CLI --set) -> overrides; values are parsed as JSON where they can be."""

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set {item!r}: expected key=value, e.g. occupancy.steps=200")
        try:
            out[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            out[key.strip()] = raw
    return out
