"""The GenICam XML of the simulated line-scan hyperspectral GigE Vision camera.

Register map: the fixed addresses Aravis's fake camera (``ArvFakeCamera``)
interprets (Width 0x100, Height 0x104, PixelFormat 0x128, ExposureTime µs
0x120, acquisition 0x124, thread wake-up period µs 0x138, trigger
0x300–0x30c), plus mehs registers at 0xF00–0xF3F that the simulator's fill
callback reads (shutter, spectral calibration, temperature, dynamic range,
TLParamsLocked, and the frame period µs that ``AcquisitionFrameRate`` sets).

The frame period is a mehs register, not Aravis's 0x138, because the simulator
drives 0x138 itself: the fake camera's thread wakes on multiples of 0x138, and
after a stall of the host the simulator shortens it to deliver the frames its
frame clock exposed meanwhile (see :mod:`mehs.capture.genicam_sim`).

References
----------
EMVA, *GenICam Standard (GenApi) 2.1*, 2016 (node types and XML schema);
EMVA, *SFNC 2.7*, 2022 (feature names); Aravis ``src/arvfakecamera.h`` (register map).
"""

from __future__ import annotations

from typing import Sequence

from mehs.capture.pixfmt import PIXEL_FORMATS

REG_WIDTH, REG_HEIGHT, REG_PIXEL_FORMAT = 0x100, 0x104, 0x128
REG_EXPOSURE_US, REG_ACQUISITION, REG_WAKE_PERIOD_US = 0x120, 0x124, 0x138
REG_SENSOR_WIDTH, REG_SENSOR_HEIGHT = 0x11C, 0x118
REG_SHUTTER = 0xF00          # 1 = open, 0 = closed
REG_WL_A, REG_WL_B, REG_WL_C = 0xF08, 0xF10, 0xF18   # IEEE-754 double, big-endian
REG_TEMPERATURE = 0xF20      # double, °C
REG_DYNAMIC_RANGE_MAX = 0xF28
REG_TL_LOCKED = 0xF30
REG_FRAME_PERIOD_US = 0xF34  # the camera's frame clock (AcquisitionFrameRate)

_HEAD = """<?xml version="1.0" encoding="utf-8"?>
<RegisterDescription ModelName="{model}" VendorName="MEHS" StandardNameSpace="None"
  SchemaMajorVersion="1" SchemaMinorVersion="0" SchemaSubMinorVersion="1"
  MajorVersion="1" MinorVersion="0" SubMinorVersion="0"
  ToolTip="mehs simulated line-scan hyperspectral camera"
  ProductGuid="0" VersionGuid="0" xmlns="http://www.genicam.org/GenApi/Version_1_0"
  xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
  xsi:schemaLocation="http://www.genicam.org/GenApi/Version_1_0 GenApiSchema.xsd">
<Category Name="Root" NameSpace="Standard">
  <pFeature>DeviceControl</pFeature><pFeature>ImageFormatControl</pFeature>
  <pFeature>AcquisitionControl</pFeature><pFeature>SpectralControl</pFeature>
  <pFeature>TransportLayerControl</pFeature>
</Category>
<Category Name="DeviceControl" NameSpace="Standard">
  <pFeature>DeviceVendorName</pFeature><pFeature>DeviceModelName</pFeature>
  <pFeature>DeviceVersion</pFeature><pFeature>DeviceSerialNumber</pFeature>
  <pFeature>DeviceTemperature</pFeature>
</Category>
<Category Name="ImageFormatControl" NameSpace="Standard">
  <pFeature>SensorWidth</pFeature><pFeature>SensorHeight</pFeature><pFeature>Width</pFeature>
  <pFeature>Height</pFeature><pFeature>OffsetY</pFeature><pFeature>BinningVertical</pFeature>
  <pFeature>PixelFormat</pFeature><pFeature>PixelDynamicRangeMax</pFeature>
</Category>
<Category Name="AcquisitionControl" NameSpace="Standard">
  <pFeature>AcquisitionMode</pFeature><pFeature>AcquisitionStart</pFeature>
  <pFeature>AcquisitionStop</pFeature><pFeature>AcquisitionFrameRate</pFeature>
  <pFeature>ExposureTime</pFeature><pFeature>TriggerSelector</pFeature>
  <pFeature>TriggerMode</pFeature><pFeature>TriggerSource</pFeature>
  <pFeature>TriggerSoftware</pFeature>{shutter_cat}
</Category>
<Category Name="SpectralControl" NameSpace="Custom">
  <pFeature>WavelengthCoefficientA</pFeature><pFeature>WavelengthCoefficientB</pFeature>
  <pFeature>WavelengthCoefficientC</pFeature>
</Category>
<Category Name="TransportLayerControl" NameSpace="Standard">
  <pFeature>PayloadSize</pFeature><pFeature>TLParamsLocked</pFeature>
</Category>
"""


def _string(name: str, addr: int, length: int) -> str:
    return (f'<StringReg Name="{name}" NameSpace="Standard"><Address>{addr:#x}</Address>'
            f'<Length>{length}</Length><AccessMode>RO</AccessMode><pPort>Device</pPort></StringReg>\n')


def _intreg(name: str, addr: int, access: str = "RW", index: str = "") -> str:
    return (f'<IntReg Name="{name}" NameSpace="Custom"><Address>{addr:#x}</Address>{index}'
            f'<Length>4</Length><AccessMode>{access}</AccessMode><pPort>Device</pPort>'
            f'<Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>\n')


def _integer(name: str, reg: str, *, lo: int | None = None, hi: int | None = None,
             locked: bool = False, access: str | None = None) -> str:
    lim = (f"<Min>{lo}</Min>" if lo is not None else "") + (f"<Max>{hi}</Max>" if hi is not None else "")
    lk = "<pIsLocked>TLParamsLocked</pIsLocked>" if locked else ""
    return f'<Integer Name="{name}" NameSpace="Standard">{lk}<pValue>{reg}</pValue>{lim}</Integer>\n'


def _floatreg(name: str, addr: int) -> str:
    return (f'<FloatReg Name="{name}" NameSpace="Custom"><Address>{addr:#x}</Address><Length>8</Length>'
            f'<AccessMode>RO</AccessMode><pPort>Device</pPort><Endianess>BigEndian</Endianess></FloatReg>\n')


def _enum(name: str, reg: str, entries: Sequence[tuple[str, int]], locked: bool = False) -> str:
    e = "".join(f'<EnumEntry Name="{n}" NameSpace="Standard"><Value>{v}</Value></EnumEntry>'
                for n, v in entries)
    lk = "<pIsLocked>TLParamsLocked</pIsLocked>" if locked else ""
    return f'<Enumeration Name="{name}" NameSpace="Standard">{lk}{e}<pValue>{reg}</pValue></Enumeration>\n'


def genicam_xml(*, samples: int, bands: int, pixel_formats: Sequence[str] = ("Mono12", "Mono16",
                "Mono12Packed", "Mono12p"), shutter: bool = True, model: str = "SIM-HS",
                max_frame_rate: float = 250.0) -> str:
    """GenICam XML of a line-scan HS camera: ``Width`` = ``samples``, ``Height`` = ``bands``.

    ``pixel_formats`` are the PixelFormat entries offered; ``shutter`` adds the
    ``Shutter`` enumeration (``Open``/``Closed``).
    """
    bad = [f for f in pixel_formats if f not in PIXEL_FORMATS]
    if bad or not pixel_formats:
        raise ValueError(f"unknown pixel formats {bad}; choose from {list(PIXEL_FORMATS)}")
    x = [_HEAD.format(model=model, shutter_cat="<pFeature>Shutter</pFeature>" if shutter else "")]
    x.append(_string("DeviceVendorName", 0x48, 32) + _string("DeviceModelName", 0x68, 32)
             + _string("DeviceVersion", 0x88, 32) + _string("DeviceSerialNumber", 0xD8, 16))
    x.append('<Float Name="DeviceTemperature" NameSpace="Standard"><pValue>DeviceTemperatureReg</pValue>'
             '<Unit>C</Unit></Float>\n' + _floatreg("DeviceTemperatureReg", REG_TEMPERATURE))
    x.append(_integer("SensorWidth", "SensorWidthReg") + _intreg("SensorWidthReg", REG_SENSOR_WIDTH, "RO"))
    x.append(_integer("SensorHeight", "SensorHeightReg")
             + _intreg("SensorHeightReg", REG_SENSOR_HEIGHT, "RO"))
    # the simulated sensor has a fixed geometry: Width/Height read-only, no binning
    x.append(_integer("Width", "WidthReg") + _intreg("WidthReg", REG_WIDTH, "RO"))
    x.append(_integer("Height", "HeightReg") + _intreg("HeightReg", REG_HEIGHT, "RO"))
    for name, v in (("OffsetY", 0), ("BinningVertical", 1)):
        x.append(f'<Integer Name="{name}" NameSpace="Standard"><Value>{v}</Value>'
                 f'<Min>{v}</Min><Max>{v}</Max></Integer>\n')
    x.append(_enum("PixelFormat", "PixelFormatReg", [(f, PIXEL_FORMATS[f]) for f in pixel_formats],
                   locked=True) + _intreg("PixelFormatReg", REG_PIXEL_FORMAT))
    x.append(_integer("PixelDynamicRangeMax", "PixelDynamicRangeMaxReg")
             + _intreg("PixelDynamicRangeMaxReg", REG_DYNAMIC_RANGE_MAX, "RO"))
    x.append('<Command Name="AcquisitionStart" NameSpace="Standard"><pValue>AcquisitionReg</pValue>'
             '<CommandValue>1</CommandValue></Command>\n'
             '<Command Name="AcquisitionStop" NameSpace="Standard"><pValue>AcquisitionReg</pValue>'
             '<CommandValue>0</CommandValue></Command>\n' + _intreg("AcquisitionReg", REG_ACQUISITION, "WO"))
    x.append(_enum("AcquisitionMode", "AcquisitionModeReg", [("Continuous", 1), ("SingleFrame", 2),
                                                             ("MultiFrame", 3)])
             + _intreg("AcquisitionModeReg", 0x12C))
    x.append('<Float Name="AcquisitionFrameRate" NameSpace="Standard">'
             f'<pValue>AcquisitionFrameRateConv</pValue>'
             f'<Min>1.0</Min><Max>{float(max_frame_rate)}</Max><Unit>Hz</Unit></Float>\n'
             '<Converter Name="AcquisitionFrameRateConv" NameSpace="Custom">'
             '<FormulaTo>(1000000 / FROM)</FormulaTo><FormulaFrom>(1000000 / TO)</FormulaFrom>'
             '<pValue>FramePeriodReg</pValue></Converter>\n'
             + _intreg("FramePeriodReg", REG_FRAME_PERIOD_US))
    x.append('<Float Name="ExposureTime" NameSpace="Standard"><pValue>ExposureTimeConv</pValue>'
             '<Min>10.0</Min><Max>10000000.0</Max><Unit>us</Unit></Float>\n'
             '<Converter Name="ExposureTimeConv" NameSpace="Custom"><FormulaTo>FROM</FormulaTo>'
             '<FormulaFrom>TO</FormulaFrom><pValue>ExposureTimeReg</pValue></Converter>\n'
             + _intreg("ExposureTimeReg", REG_EXPOSURE_US))
    idx = '<pIndex Offset="0x20">TriggerSelectorInteger</pIndex>'
    x.append(_enum("TriggerSelector", "TriggerSelectorInteger", [("FrameStart", 0), ("AcquisitionStart", 1)])
             + '<Integer Name="TriggerSelectorInteger" NameSpace="Custom"><Value>0</Value></Integer>\n')
    x.append(_enum("TriggerMode", "TriggerModeReg", [("Off", 0), ("On", 1)])
             + _intreg("TriggerModeReg", 0x300, index=idx))
    x.append(_enum("TriggerSource", "TriggerSourceReg", [("Line0", 0), ("Software", 1)])
             + _intreg("TriggerSourceReg", 0x304, index=idx))
    x.append('<Command Name="TriggerSoftware" NameSpace="Standard"><pValue>TriggerSoftwareReg</pValue>'
             '<CommandValue>1</CommandValue></Command>\n' + _intreg("TriggerSoftwareReg", 0x30C, "WO"))
    if shutter:
        x.append(_enum("Shutter", "ShutterReg", [("Closed", 0), ("Open", 1)])
                 + _intreg("ShutterReg", REG_SHUTTER))
    for n, a in (("A", REG_WL_A), ("B", REG_WL_B), ("C", REG_WL_C)):
        x.append(f'<Float Name="WavelengthCoefficient{n}" NameSpace="Custom">'
                 f'<pValue>WavelengthCoefficient{n}Reg</pValue></Float>\n'
                 + _floatreg(f"WavelengthCoefficient{n}Reg", a))
    x.append('<IntSwissKnife Name="PayloadSize" NameSpace="Standard"><pVariable Name="W">Width</pVariable>'
             '<pVariable Name="H">Height</pVariable><pVariable Name="PF">PixelFormatReg</pVariable>'
             '<Formula>(W * H * ((PF &gt;&gt; 16) &amp; 255) + 7) / 8</Formula></IntSwissKnife>\n')
    x.append(_integer("TLParamsLocked", "TLParamsLockedReg", lo=0, hi=1)
             + _intreg("TLParamsLockedReg", REG_TL_LOCKED))
    x.append('<Port Name="Device" NameSpace="Standard"/>\n</RegisterDescription>\n')
    return "".join(x)
