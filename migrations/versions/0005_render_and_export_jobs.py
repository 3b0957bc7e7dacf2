"""render and export jobs on finished training jobs (issue 20)

A job has a kind (train, render, export) and, for a render or export, the training job it works on
(`parent_id`, deleted with it). Existing jobs are training jobs. SQLite cannot add a foreign key or a CHECK to
a table, so there the table is rebuilt by copying it (batch mode), keeping AUTOINCREMENT (migration 0004).

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-25
"""
import sqlalchemy as sa
from alembic import op


revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None


def batch():
    sqlite = op.get_bind().dialect.name == 'sqlite'
    if sqlite and op.get_bind().exec_driver_sql('PRAGMA foreign_keys').scalar():
        raise RuntimeError('foreign keys are on for this connection: rebuilding jobs would cascade-delete rows')
    return op.batch_alter_table('jobs', table_kwargs={'sqlite_autoincrement': True} if sqlite else {})


def upgrade() -> None:
    with batch() as jobs:
        jobs.add_column(sa.Column('kind', sa.String(length=16), server_default='train', nullable=False))
        jobs.add_column(sa.Column('parent_id', sa.Integer(), nullable=True))
        jobs.create_foreign_key('fk_jobs_parent_id_jobs', 'jobs', ['parent_id'], ['id'], ondelete='CASCADE')
        jobs.create_index('ix_jobs_parent_id', ['parent_id'])
        jobs.create_check_constraint('kind_valid', "kind IN ('train', 'render', 'export')")


def downgrade() -> None:
    with batch() as jobs:
        jobs.drop_constraint('kind_valid', type_='check')
        jobs.drop_index('ix_jobs_parent_id')
        jobs.drop_constraint('fk_jobs_parent_id_jobs', type_='foreignkey')
        jobs.drop_column('parent_id')
        jobs.drop_column('kind')
