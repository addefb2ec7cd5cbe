"""Version 2: cutouts, each event's sky cutout per band, made from the TOD.

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-06
"""
import sqlalchemy as sa
from alembic import op
from sqlalchemy import Text
from sqlalchemy.dialects import postgresql

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade():
    op.create_table('cutouts',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('observation_id', sa.Integer(), nullable=False, comment='the observation it was ingested with'),
    sa.Column('source_id', sa.Integer(), nullable=False, comment='persistent source'),
    sa.Column('run_event_id', sa.BigInteger(), nullable=True, comment='the event'),
    sa.Column('event_uuid', sa.Text(), nullable=True, comment='its UUID (as in events, alerts and the database)'),
    sa.Column('source_uuid', sa.Text(), nullable=True, comment="its source's UUID"),
    sa.Column('bandpass', sa.Text(), nullable=True, comment='band'),
    sa.Column('obs_id', sa.Text(), nullable=True, comment='observation of the crossing'),
    sa.Column('wafer_slot', sa.Text(), nullable=True, comment='wafer of the crossing'),
    sa.Column('ctime', sa.Double(), nullable=True, comment="the crossing's centre: the event's highest forced S/N in this band [s]"),
    sa.Column('time', sa.Text(), nullable=True, comment='the same as ISO UTC (lightcurvedb Cutout time)'),
    sa.Column('frequency', sa.BigInteger(), nullable=True, comment="band as lightcurvedb's integer frequency [GHz]"),
    sa.Column('flux', sa.Double(), nullable=True, comment='forced flux at that crossing [mJy]'),
    sa.Column('snr', sa.Double(), nullable=True, comment='its S/N'),
    sa.Column('beam_fwhm', sa.Double(), nullable=True, comment="the band's beam FWHM (the detectors' median) [arcmin]"),
    sa.Column('peak_ra', sa.Double(), nullable=True, comment="RA of the cutout's brightest pixel [deg]"),
    sa.Column('peak_dec', sa.Double(), nullable=True, comment="Dec of the cutout's brightest pixel [deg]"),
    sa.Column('peak_offset', sa.Double(), nullable=True, comment="that pixel's distance from the event's position [arcmin]"),
    sa.Column('file', sa.Text(), nullable=True, comment='FITS file of the cutout, relative to the events folder: the binned filtered amplitude (mJy) with its WCS, and its weights (1/mJy^2) in HDU WEIGHT'),
    sa.Column('streams', sa.Text(), nullable=True, comment='NPZ file of the detector time streams of its crossings at the detection S/N (at least this one): so_transients.events.cutouts.crossings_of'),
    sa.Column('data', sa.JSON().with_variant(postgresql.JSONB(astext_type=Text()), 'postgresql'), nullable=True, comment='the cutout in Jy, rows of pixels, null where nothing fell (lightcurvedb Cutout data)'),
    sa.Column('wcs', sa.Text(), nullable=True, comment='its FITS WCS header'),
    sa.Column('extra', sa.JSON().with_variant(postgresql.JSONB(astext_type=Text()), 'postgresql'), nullable=True, comment='columns of the cutouts file no declaration names'),
    sa.ForeignKeyConstraint(['observation_id'], ['observations.id'], ondelete='CASCADE'),
    sa.ForeignKeyConstraint(['source_id'], ['sources.id'], ),
    sa.PrimaryKeyConstraint('id'),
    sa.UniqueConstraint('observation_id', 'run_event_id', 'bandpass')
    )
    op.create_index(op.f('ix_cutouts_observation_id'), 'cutouts', ['observation_id'], unique=False)
    op.create_index(op.f('ix_cutouts_source_id'), 'cutouts', ['source_id'], unique=False)
