"""scenes posed from photos

A scene registered from an archive of photos (POST /v1/scenes/photos) is 'posing' while its poses job
runs, then 'ready' (or 'failed'). The scenes' state CHECK gains the value; SQLite cannot alter a constraint in
place, so the table is rebuilt by copying it (batch mode), keeping AUTOINCREMENT.

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-06
"""
from alembic import op


revision = '0008'
down_revision = '0007'
branch_labels = None
depends_on = None


def batch():
    sqlite = op.get_bind().dialect.name == 'sqlite'
    if sqlite and op.get_bind().exec_driver_sql('PRAGMA foreign_keys').scalar():
        raise RuntimeError('foreign keys are on for this connection: rebuilding scenes would break its jobs')
    return op.batch_alter_table('scenes', table_kwargs={'sqlite_autoincrement': True} if sqlite else {})


def upgrade() -> None:
    with batch() as scenes:
        scenes.drop_constraint('state_valid', type_='check')
        scenes.create_check_constraint('state_valid', "state IN ('generating', 'posing', 'ready', 'failed')")


def downgrade() -> None:
    op.execute("UPDATE scenes SET state = 'failed', error = 'posing was stopped by a downgrade' WHERE state = 'posing'")
    with batch() as scenes:
        scenes.drop_constraint('state_valid', type_='check')
        scenes.create_check_constraint('state_valid', "state IN ('generating', 'ready', 'failed')")
