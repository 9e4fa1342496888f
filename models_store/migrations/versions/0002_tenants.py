"""Tenants: every actor, model and job belongs to one (issue 16).

Existing rows belong to the tenant ``default`` (what a token without a tenant maps to).
Clips and input rigs belong to their actor's tenant, artifacts to their job's.

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-01

"""
from typing import Sequence, Union

from alembic import op
import sqlalchemy as sa


# revision identifiers, used by Alembic.
revision: str = '0002'
down_revision: Union[str, Sequence[str], None] = '0001'
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None

TABLES = ('actors', 'models', 'jobs')


def upgrade() -> None:
    """Add ``tenant`` (default ``'default'``, indexed) to actors, models and jobs."""
    for table in TABLES:
        with op.batch_alter_table(table) as batch:
            batch.add_column(sa.Column('tenant', sa.String(length=64), nullable=False,
                                       server_default='default'))
            batch.create_index(op.f(f'ix_{table}_tenant'), ['tenant'])


def downgrade() -> None:
    """Drop the tenant columns."""
    for table in TABLES:
        with op.batch_alter_table(table) as batch:
            batch.drop_index(op.f(f'ix_{table}_tenant'))
            batch.drop_column('tenant')
