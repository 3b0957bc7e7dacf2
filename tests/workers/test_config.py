"""The job config's own defaults: the smoke profile's short validation fit, and what a saved config
keeps."""

from workers.config import SMOKE_APPEARANCE_STEPS, TrainConfig


def test_the_smoke_profile_fits_validation_appearance_briefly_unless_told():
    assert SMOKE_APPEARANCE_STEPS == 4
    assert TrainConfig(method="leco", profile="smoke").val_appearance_steps == 4
    assert TrainConfig(method="leco").val_appearance_steps == 32  # the cpu profile
    assert TrainConfig(method="leco", profile="paper").val_appearance_steps == 32
    # a value given is kept, the default's included
    told = TrainConfig(method="switch", profile="smoke", val_appearance_steps=32)
    assert told.val_appearance_steps == 32
    # a saved config (run.json) loads with the value it trained with
    again = TrainConfig.model_validate_json(told.model_dump_json())
    assert again == told
    # as the API reads a request body
    body = {"method": "switch", "profile": "smoke", "overrides": {"main_steps": 5}}
    assert TrainConfig.model_validate(body).val_appearance_steps == 4
    described = TrainConfig.model_json_schema()["properties"]["val_appearance_steps"]
    assert "4 when not given at the smoke profile" in described["description"]
