"""Conditional requests (RFC 9110, section 13.1.2): whether If-None-Match lets a download answer
304. `*` matches any current representation; otherwise a list of entity tags, each strong or weak
(`W/"..."`), compared weakly, as a GET's If-None-Match is (section 8.8.3.2). A tag may hold a
comma, so the list is read tag by tag, not split on commas."""

from __future__ import annotations

import re

# one entity tag: optional W/, then a quoted opaque tag (any visible character but DQUOTE)
TAG = re.compile(r'\s*(?:W/)?"([\x21\x23-\x7e\x80-\xff]*)"\s*(?:,|$)')


def opaque_tags(header: str) -> list[str] | None:
    """The opaque tags of an If-None-Match list, or None when it is not one (then it is ignored,
    as a recipient ignores a malformed precondition)."""
    tags, at = [], 0
    header = header.strip()
    while at < len(header):
        match = TAG.match(header, at)
        if match is None:
            return None
        tags.append(match.group(1))
        at = match.end()
    return tags


def none_match_fails(header: str | None, etag: str) -> bool:
    """True when If-None-Match names the current representation (ETAG, a strong `"..."`): the
    answer to a GET or HEAD is then 304 Not Modified."""
    if header is None:
        return False
    if header.strip() == "*":
        return True
    tags = opaque_tags(header)
    return tags is not None and etag.strip('"') in tags
