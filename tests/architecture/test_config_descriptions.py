"""Every setting a user can give a job has a description: it fills the OpenAPI schema, `leco
settings` and the `--set` help."""

from pydantic import BaseModel

from model.profiles import Profile
from workers.config import TrainConfig
from workers.render.camera_paths.registry import PATH_KINDS
from workers.render.schemas import ExportConfig, RenderConfig, ViewRequest


def undescribed(model: type[BaseModel], prefix: str = "") -> list[str]:
    missing = []
    for name, field in model.model_fields.items():
        nested = field.annotation
        if isinstance(nested, type) and issubclass(nested, BaseModel):
            missing += undescribed(nested, f"{prefix}{name}.")
        elif not field.description and name != "kind":  # a path's `kind` tag is its name
            missing.append(prefix + name)
    return missing


def test_every_setting_of_every_job_schema_has_a_description():
    schemas = [TrainConfig, Profile, RenderConfig, ViewRequest, ExportConfig, *PATH_KINDS.values()]
    missing = [f"{s.__name__}: {name}" for s in schemas for name in undescribed(s)]
    assert missing == []


def test_the_openapi_schema_carries_the_descriptions():
    schema = TrainConfig.model_json_schema()
    assert "dotted key" in schema["properties"]["overrides"]["description"]
    guided = Profile.model_json_schema()["$defs"]["GuidedConfig"]["properties"]
    assert "p(E_e)" in guided["empty_threshold"]["description"]


def test_leco_settings_lists_every_key_an_override_takes(capsys):
    from cli.main import main
    from model.profiles import PROFILES, settings

    rows = settings(PROFILES["cpu"])
    assert (
        "guided.dilate",
        1,
        "also keep bins up to this many bins before / after a kept bin",
    ) in rows
    for key, value, _ in rows:  # every listed key is one a job may override, with its own value
        config = TrainConfig(method="leco", profile="cpu", overrides={key: value})
        assert config.resolved_profile() == PROFILES["cpu"]
    assert main(["settings", "occupancy.w_"]) == 0
    out = capsys.readouterr().out
    assert "occupancy.w_g" in out and "imbalanced gate loss" in out and "guided." not in out


def test_a_mistyped_override_names_the_setting_it_was_close_to():
    import pytest
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match=r"guided.dilat'.*did you mean guided.dilate\?"):
        TrainConfig(method="leco", overrides={"guided.dilat": 2})
    with pytest.raises(ValidationError, match=r"no such setting.*`leco settings` lists them"):
        TrainConfig(method="leco", overrides={"guided.zzzq": 2})
