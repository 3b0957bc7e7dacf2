"""job kinds are the registry's, not a CHECK constraint's

A job's kind names an entry of service/jobs/kinds.py; the API refuses any other before a row is written. A
CHECK listing the built-in kinds would refuse a kind added by a new file and a registry line, so it goes. SQLite
cannot drop a constraint in place: the table is rebuilt by copying it (batch mode), keeping AUTOINCREMENT.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-26
"""
from alembic import op


revision = '0007'
down_revision = '0006'
branch_labels = None
depends_on = None


def batch():
    sqlite = op.get_bind().dialect.name == 'sqlite'
    if sqlite and op.get_bind().exec_driver_sql('PRAGMA foreign_keys').scalar():
        raise RuntimeError('foreign keys are on for this connection: rebuilding jobs would cascade-delete rows')
    return op.batch_alter_table('jobs', table_kwargs={'sqlite_autoincrement': True} if sqlite else {})


def upgrade() -> None:
    with batch() as jobs:
        jobs.drop_constraint('kind_valid', type_='check')


def downgrade() -> None:
    with batch() as jobs:
        jobs.create_check_constraint('kind_valid', "kind IN ('train', 'render', 'export')")
