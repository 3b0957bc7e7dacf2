"""SQLite: the ids of scenes, jobs and artifacts are never given out again (AUTOINCREMENT)

Without it SQLite gives a new row the largest id + 1, so deleting the newest job and submitting another gave
the new one the deleted one's id: a client, a dashboard or an idempotent replay still holding the old id was
shown a different job (found by the stateful API fuzz). PostgreSQL's sequences never hand an id out twice;
nothing changes there. SQLite cannot alter a table's key, so each table is rebuilt by copying it (Alembic's
batch mode); the rows and their ids are kept, and new ids start after the largest one kept.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-28
"""
from alembic import op


revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None

TABLES = ('scenes', 'jobs', 'artifacts')


def rebuild(autoincrement: bool) -> None:
    bind = op.get_bind()
    if bind.dialect.name != 'sqlite':
        return
    # Dropping the old `jobs` with foreign keys on would delete every phase, metric and artifact row with it
    # (ON DELETE CASCADE). The migration's own connection has them off (SQLite's default); make sure.
    if bind.exec_driver_sql('PRAGMA foreign_keys').scalar():
        raise RuntimeError('foreign keys are on for this connection: rebuilding jobs would cascade-delete rows')
    for table in TABLES:
        with op.batch_alter_table(table, recreate='always',
                                  table_kwargs={'sqlite_autoincrement': autoincrement}):
            pass


def upgrade() -> None:
    rebuild(autoincrement=True)


def downgrade() -> None:
    rebuild(autoincrement=False)
