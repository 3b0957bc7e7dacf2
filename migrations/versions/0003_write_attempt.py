"""the attempt that wrote each metric and artifact (issue 17, fencing)

A run's writes are refused unless its attempt still holds the job; the column records which attempt each row
came from, so "one writer per step" can be checked after a fault. Rows from before have NULL.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-24
"""
import sqlalchemy as sa
from alembic import op


revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column('metrics', sa.Column('attempt', sa.Integer(), nullable=True))
    op.add_column('artifacts', sa.Column('attempt', sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('artifacts') as batch:
        batch.drop_column('attempt')
    with op.batch_alter_table('metrics') as batch:
        batch.drop_column('attempt')
