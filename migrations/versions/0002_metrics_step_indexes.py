"""metrics indexes for polling: (job_id, step) and (job_id, phase, step)

Dashboards poll `metrics?after_step=N` and the job view asks for the latest step of each phase; without these
both scanned every metric row of the job (a long job has hundreds of thousands).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-23
"""
from alembic import op


revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index('ix_metrics_job_step', 'metrics', ['job_id', 'step'])
    op.create_index('ix_metrics_job_phase_step', 'metrics', ['job_id', 'phase', 'step'])


def downgrade() -> None:
    op.drop_index('ix_metrics_job_phase_step', table_name='metrics')
    op.drop_index('ix_metrics_job_step', table_name='metrics')
