"""If-None-Match read as RFC 9110 reads it (service/api/conditional.py): `*`, weak tags, lists, a
comma inside a tag, and a malformed header ignored."""

import pytest

from service.api.conditional import none_match_fails, opaque_tags

ETAG = '"abc123"'


@pytest.mark.parametrize(
    "header, matches",
    [
        (None, False),
        ('"abc123"', True),
        ("*", True),
        (" * ", True),
        ('W/"abc123"', True),  # weak comparison: a weak validator of the same tag matches
        ('"zzz", W/"abc123"', True),
        ('"zzz" ,"abc123" ', True),
        ('"zzz"', False),
        ('"abc"', False),
        ('"abc123', False),  # malformed: ignored, the whole body is sent
        ("abc123", False),
        ('"a,b", "abc123"', True),  # a comma inside a tag is part of the tag
        ("", False),
    ],
)
def test_if_none_match_answers_304_for_the_current_tag_star_and_weak_validators(header, matches):
    assert none_match_fails(header, ETAG) is matches


def test_a_list_is_read_tag_by_tag():
    assert opaque_tags('"a,b" , W/"c"') == ["a,b", "c"]
    assert opaque_tags('"a" "b"') is None  # tags must be separated by commas
