"""scene names are never all digits

A name of digits alone reads as an id wherever a scene is referenced, so it reached (and could delete) the
scene with that id. Registration now refuses such names; existing ones are renamed 'scene-<name>' (or
'scene-<name>-<id>' when that is taken or too long, 'scene-id-<id>'). Jobs reference scenes by id, so nothing else changes.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-25
"""
import sqlalchemy as sa
from alembic import op


revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None


def upgrade() -> None:
    bind = op.get_bind()
    rows = bind.execute(sa.text('SELECT id, name FROM scenes')).all()
    taken = {name for _, name in rows}
    for scene_id, name in rows:
        if not (name.isascii() and name.isdigit()):
            continue
        candidates = [f'scene-{name}', f'scene-{name}-{scene_id}', f'scene-id-{scene_id}']
        new = next(c for c in candidates if c not in taken and len(c) <= 128)
        taken.add(new)
        bind.execute(sa.text('UPDATE scenes SET name = :new WHERE id = :id'), {'new': new, 'id': scene_id})


def downgrade() -> None:
    pass  # the old names read as ids; they are not restored
