"""Initial schema: actors, clips, input rigs, models, jobs, artifacts.

Revision ID: 0001
Revises:
Create Date: 2026-11-23

"""
from typing import Sequence, Union

from alembic import op
import sqlalchemy as sa


# revision identifiers, used by Alembic.
revision: str = '0001'
down_revision: Union[str, Sequence[str], None] = None
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None


def upgrade() -> None:
    """Create the tables."""
    op.create_table('actors',
    sa.Column('id', sa.String(length=32), nullable=False),
    sa.Column('name', sa.String(length=200), nullable=False),
    sa.Column('metadata', sa.JSON(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('neutral_blob', sa.String(length=512), nullable=True),
    sa.Column('neutral_sha256', sa.String(length=64), nullable=True),
    sa.Column('vertex_count', sa.Integer(), nullable=True),
    sa.Column('triangle_count', sa.Integer(), nullable=True),
    sa.Column('markers_blob', sa.String(length=512), nullable=True),
    sa.Column('markers_sha256', sa.String(length=64), nullable=True),
    sa.Column('marker_count', sa.Integer(), nullable=True),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_actors'))
    )
    op.create_table('jobs',
    sa.Column('id', sa.String(length=32), nullable=False),
    sa.Column('kind', sa.String(length=32), nullable=False),
    sa.Column('actor_id', sa.String(length=32), nullable=False),
    sa.Column('model_id', sa.String(length=32), nullable=True),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('progress', sa.Float(), nullable=False),
    sa.Column('stage', sa.String(length=200), nullable=False),
    sa.Column('payload', sa.JSON(), nullable=False),
    sa.Column('result', sa.JSON(), nullable=True),
    sa.Column('error', sa.JSON(), nullable=True),
    sa.Column('attempts', sa.Integer(), nullable=False),
    sa.Column('worker', sa.String(length=200), nullable=True),
    sa.Column('lease_expires_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('cancel_requested', sa.Boolean(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('started_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('finished_at', sa.DateTime(timezone=True), nullable=True),
    sa.CheckConstraint("status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')",
                       name=op.f('ck_jobs_status')),
    sa.CheckConstraint('progress >= 0 AND progress <= 1', name=op.f('ck_jobs_progress')),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_jobs'))
    )
    op.create_index(op.f('ix_jobs_actor_id'), 'jobs', ['actor_id'])
    op.create_index(op.f('ix_jobs_kind'), 'jobs', ['kind'])
    op.create_index(op.f('ix_jobs_model_id'), 'jobs', ['model_id'])
    op.create_index(op.f('ix_jobs_status_created_at'), 'jobs', ['status', 'created_at'])
    op.create_table('artifacts',
    sa.Column('id', sa.String(length=32), nullable=False),
    sa.Column('job_id', sa.String(length=32), nullable=False),
    sa.Column('media_type', sa.String(length=200), nullable=False),
    sa.Column('filename', sa.String(length=200), nullable=True),
    sa.Column('blob', sa.String(length=512), nullable=False),
    sa.Column('size_bytes', sa.BigInteger(), nullable=False),
    sa.Column('sha256', sa.String(length=64), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['job_id'], ['jobs.id'], name=op.f('fk_artifacts_job_id_jobs')),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_artifacts'))
    )
    op.create_index(op.f('ix_artifacts_job_id'), 'artifacts', ['job_id'])
    op.create_table('clips',
    sa.Column('id', sa.String(length=32), nullable=False),
    sa.Column('actor_id', sa.String(length=32), nullable=False),
    sa.Column('name', sa.String(length=200), nullable=True),
    sa.Column('frames', sa.Integer(), nullable=False),
    sa.Column('blob', sa.String(length=512), nullable=False),
    sa.Column('sha256', sa.String(length=64), nullable=False),
    sa.Column('size_bytes', sa.BigInteger(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['actor_id'], ['actors.id'], name=op.f('fk_clips_actor_id_actors')),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_clips'))
    )
    op.create_index(op.f('ix_clips_actor_id'), 'clips', ['actor_id'])
    op.create_table('input_rigs',
    sa.Column('id', sa.String(length=32), nullable=False),
    sa.Column('actor_id', sa.String(length=32), nullable=False),
    sa.Column('name', sa.String(length=200), nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('mesh_blob', sa.String(length=512), nullable=False),
    sa.Column('mesh_sha256', sa.String(length=64), nullable=False),
    sa.Column('registration_blob', sa.String(length=512), nullable=True),
    sa.Column('registration_sha256', sa.String(length=64), nullable=True),
    sa.Column('error', sa.JSON(), nullable=True),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.CheckConstraint("status IN ('registering', 'ready', 'failed')",
                       name=op.f('ck_input_rigs_status')),
    sa.ForeignKeyConstraint(['actor_id'], ['actors.id'],
                            name=op.f('fk_input_rigs_actor_id_actors')),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_input_rigs')),
    sa.UniqueConstraint('actor_id', 'name', name=op.f('uq_input_rigs_actor_id_name'))
    )
    op.create_index(op.f('ix_input_rigs_actor_id'), 'input_rigs', ['actor_id'])
    op.create_table('models',
    sa.Column('id', sa.String(length=32), nullable=False),
    sa.Column('actor_id', sa.String(length=32), nullable=False),
    sa.Column('kind', sa.String(length=32), nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('params', sa.JSON(), nullable=False),
    sa.Column('metrics', sa.JSON(), nullable=True),
    sa.Column('size_bytes', sa.BigInteger(), nullable=True),
    sa.Column('blob', sa.String(length=512), nullable=True),
    sa.Column('sha256', sa.String(length=64), nullable=True),
    sa.Column('error', sa.JSON(), nullable=True),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.CheckConstraint("status IN ('training', 'ready', 'failed')", name=op.f('ck_models_status')),
    sa.ForeignKeyConstraint(['actor_id'], ['actors.id'], name=op.f('fk_models_actor_id_actors')),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_models'))
    )
    op.create_index(op.f('ix_models_actor_id'), 'models', ['actor_id'])


def downgrade() -> None:
    """Drop the tables."""
    op.drop_index(op.f('ix_models_actor_id'), table_name='models')
    op.drop_table('models')
    op.drop_index(op.f('ix_input_rigs_actor_id'), table_name='input_rigs')
    op.drop_table('input_rigs')
    op.drop_index(op.f('ix_clips_actor_id'), table_name='clips')
    op.drop_table('clips')
    op.drop_index(op.f('ix_artifacts_job_id'), table_name='artifacts')
    op.drop_table('artifacts')
    op.drop_index(op.f('ix_jobs_status_created_at'), table_name='jobs')
    op.drop_index(op.f('ix_jobs_model_id'), table_name='jobs')
    op.drop_index(op.f('ix_jobs_kind'), table_name='jobs')
    op.drop_index(op.f('ix_jobs_actor_id'), table_name='jobs')
    op.drop_table('jobs')
    op.drop_table('actors')
