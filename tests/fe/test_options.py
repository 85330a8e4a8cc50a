"""The FE options dataclasses' messages for a bad path or address (femcal.fe.options)."""

from __future__ import annotations

import pytest

from femcal.errors import ConfigError
from femcal.fe.options import CampaignOptions

#: The start of run_campaign's message for a scratch_dir that is not a path.
NOT_A_PATH = r"^run_campaign: scratch_dir: expected a path \(a non-empty string\), got "


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"scratch_dir": ""}, NOT_A_PATH + r"'' \(str\)\.$"),
        ({"scratch_dir": 3}, NOT_A_PATH + r"3 \(int\)\.$"),
        (
            {"scheduler_address": "localhost:8786"},
            r"^run_campaign: scheduler_address: expected a Dask scheduler address tcp://host:port, "
            r"got 'localhost:8786': no protocol; write tcp://localhost:8786\.$",
        ),
    ],
)
def test_a_bad_path_or_address_is_named_with_what_was_given(options, message):
    with pytest.raises(ConfigError, match=message):
        CampaignOptions(**options)
