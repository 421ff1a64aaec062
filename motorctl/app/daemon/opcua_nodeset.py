"""OPC 40502 (OPC UA for CNC Systems) as facts: the types, DataTypes and instance declarations
of the OPC Foundation's published NodeSet (``CNC/Opc.Ua.CNC.NodeSet.xml`` of the
OPCFoundation/UA-Nodeset repository, model ``http://opcfoundation.org/UA/CNC`` 1.0.0 of
2017-06-19), written out by hand from it; data only, no asyncua (docs/opcua.md).

Why facts and not the file: asyncua's ``import_xml`` refuses that NodeSet (checked with asyncua
1.1.8: BadParentNodeIdInvalid at ``Axes``, ``ns=1;i=5004``, an example object without a parent),
and it also carries example instances (``test``, ``Channel_1``, ``X2`` ... and one with the NodeId
``ns=1;s=CncInterface.CncAxisList.X``, the very string NodeId this server gives its X axis) that
are no part of a machine. What a client relies on is here: NodeIds of the types and DataTypes,
BrowseNames, DataTypes, type definitions, modelling rules and the default EngineeringUnits.

:data:`CNC_CHILDREN` holds, per type, every child with ModellingRule Mandatory in the NodeSet, and
the Optional ones this server serves (:data:`OPTIONAL_SERVED`); a child is ``(BrowseName, kind,
DataType, EngineeringUnits)``:

* kind ``object``: an Object (DataType: its ObjectType's BrowseName);
* ``property``: a PropertyType variable (HasProperty);
* ``item``: a DataItemType variable (OPC 10000-8 5.3.1);
* ``analog``: an AnalogItemType variable (OPC 10000-8 5.3.2.3) with its mandatory ``EURange``
  (Range) and, where the NodeSet gives units, ``EngineeringUnits`` (EUInformation), both
  properties in namespace 0;
* ``position``: a CncPositionVariableType variable (DataType CncPositionDataType) with its
  ``ActPos``, ``CmdPos``, ``RemDist`` (Double) and its ``EngineeringUnits`` and ``EURange``
  properties, which the NodeSet names in the CNC namespace (``1:EngineeringUnits`` there);
* ``variable``: a BaseDataVariableType variable.

DataTypes are OPC 10000-3/-5 built-in names (``Double``, ``Boolean``, ``UInt32``, ``String``,
``NodeId``; ``[]`` after one: an array, ValueRank 1) or the BrowseName of a CNC DataType.
"""

from __future__ import annotations

#: the namespace of the CNC types and objects (OPC 40502's namespace URI, as its NodeSet has it)
CNC_NS = "http://opcfoundation.org/UA/CNC"
#: OPC 40502's ObjectTypes: (numeric NodeId in CNC_NS, BrowseName, supertype: a NodeId number
#: in CNC_NS, or "base" for BaseObjectType i=58, abstract), supertypes first
CNC_OBJECT_TYPES = ((1001, "CncComponentType", "base", True), (1003, "CncDriveType", 1001, True),
                    (1004, "CncAxisType", 1003, False), (1005, "CncSpindleType", 1003, False),
                    (1002, "CncChannelType", 1001, False), (1007, "CncInterfaceType", "base", False),
                    (1008, "CncAxisListType", "base", False), (1009, "CncSpindleListType", "base", False),
                    (1010, "CncChannelListType", "base", False))
#: CncPositionVariableType (a BaseDataVariableType of DataType CncPositionDataType, a Structure
#: of ActPos, CmdPos, RemDist: Double)
CNC_POSITION_VARIABLE_TYPE, CNC_POSITION_DATA_TYPE = 2001, 3007
#: OPC 40502's enumeration DataTypes (NodeId number in CNC_NS, BrowseName, the values 0, 1, ...)
CNC_ENUMS = ((3001, "CncSpindleTurnDirection", ("None", "CW", "CCW")),
             (3002, "CncChannelProgramStatus", ("Stopped", "Running", "Waiting", "Interrupted", "Canceled")),
             (3003, "CncChannelStatus", ("Active", "Interrupted", "Reset")),
             (3004, "CncAxisStatus", ("InPosition", "Moving", "Parked")),
             (3005, "CncSpindleStatus", ("Stopped", "InTargetArea", "Accelerating", "Decelerating", "Parked")),
             (3006, "CncOperationMode", ("Manual", "MDA", "Automatic")))

#: EngineeringUnits (OPC 10000-8 5.6.3: UNECE Recommendation 20 common codes as UnitId, in the
#: namespace :data:`UNECE_NS`): (UnitId, DisplayName, Description)
UNECE_NS = "http://www.opcfoundation.org/UA/units/un/cefact"
EU_METRE = (5067858, "m", "metre")                           # MTR
EU_METRE_PER_SECOND = (5067859, "m/s", "metre per second")   # MTS
EU_SECOND = (5457219, "s", "second")                         # SEC
EU_PERCENT = (20529, "%", "percent")                         # P1
EU_WATT = (5723220, "W", "watt")                             # WTT
EU_NEWTON_METRE = (20053, "N·m", "newton metre")             # NU
EU_MILLIMETRE = (5066068, "mm", "millimetre")                # MMT
EU_MM_PER_MINUTE = (4732977, "mm/min", "millimetre per minute")   # H81
EU_PER_MINUTE = (4405556, "min⁻¹", "reciprocal minute")      # C94

#: the instance declarations of each type (module docstring): the NodeSet's Mandatory children,
#: and the Optional ones in OPTIONAL_SERVED
CNC_CHILDREN: dict[str, tuple] = {
    "CncInterfaceType": (
        ("CncAxisList", "object", "CncAxisListType", None),
        ("CncChannelList", "object", "CncChannelListType", None),
        ("CncSpindleList", "object", "CncSpindleListType", None),
        ("VendorName", "property", "String", None),
        ("VendorRevision", "property", "String", None),
        ("Version", "property", "String", None),
        ("CncTypeName", "property", "String", None)),
    "CncDriveType": (
        ("ActChannel", "item", "NodeId", None),
        ("ActLoad", "analog", "Double", EU_PERCENT),
        ("ActPower", "analog", "Double", EU_WATT),
        ("ActTorque", "analog", "Double", EU_NEWTON_METRE),
        ("CmdTorque", "analog", "Double", EU_NEWTON_METRE),
        ("IsInactive", "item", "Boolean", None),
        ("IsVirtual", "item", "Boolean", None)),
    "CncAxisType": (
        ("ActStatus", "item", "CncAxisStatus", None),
        ("IsReferenced", "item", "Boolean", None),
        ("IsRotational", "item", "Boolean", None),
        ("PosDirect", "position", "CncPositionDataType", None),
        ("PosIndirect", "position", "CncPositionDataType", None),
        ("ZeroOffset", "analog", "Double", EU_MILLIMETRE)),
    "CncSpindleType": (
        ("ActGear", "item", "UInt32", None),
        ("ActOverride", "analog", "Double", None),
        ("ActSpeed", "analog", "Double", EU_PER_MINUTE),
        ("ActStatus", "item", "CncSpindleStatus", None),
        ("ActTurnDirection", "item", "CncSpindleTurnDirection", None),
        ("AnglePos", "position", "CncPositionDataType", None),
        ("CmdGear", "item", "UInt32", None),
        ("CmdOverride", "analog", "Double", None),
        ("CmdSpeed", "analog", "Double", EU_PER_MINUTE)),
    "CncChannelType": (
        ("ActFeedrate", "analog", "Double", EU_MM_PER_MINUTE),
        ("ActGFunctions", "item", "UInt32[]", None),
        ("ActJogIncrement", "analog", "Double", EU_MILLIMETRE),
        ("ActMainProgramFile", "item", "String", None),
        ("ActMainProgramLine", "item", "String", None),
        ("ActMainProgramName", "item", "String", None),
        ("ActMFunctions", "item", "UInt32[]", None),
        ("ActModalOffsetFunction", "item", "UInt32", None),
        ("ActOperationMode", "item", "CncOperationMode", None),
        ("ActOverride", "analog", "Double", EU_PERCENT),
        ("ActProgramBlock", "item", "String[]", None),
        ("ActProgramFile", "item", "String", None),
        ("ActProgramLine", "item", "String", None),
        ("ActProgramName", "item", "String", None),
        ("ActProgramStatus", "item", "CncChannelProgramStatus", None),
        ("ActStatus", "item", "CncChannelStatus", None),
        ("BlockMode", "item", "Boolean", None),
        ("CmdFeedrate", "analog", "Double", EU_MM_PER_MINUTE),
        ("CmdOperationMode", "item", "CncOperationMode", None),
        ("CmdOverride", "analog", "Double", EU_PERCENT),
        ("DryRunFeed", "analog", "Double", EU_MM_PER_MINUTE),
        ("FeedHold", "item", "Boolean", None),
        ("Id", "property", "UInt32", None),
        *((f"PosTcp{frame}{c}", "position", "CncPositionDataType", None)
          for frame in ("Bcs", "Wcs") for c in "ABCXYZ"),
        ("ToolId", "item", "UInt32", None)),
}
#: the children of CncPositionVariableType (each a CncPositionVariable's own): (BrowseName, kind,
#: DataType); EngineeringUnits and EURange in the CNC namespace, as the NodeSet names them
CNC_POSITION_CHILDREN = (("ActPos", "variable", "Double"), ("CmdPos", "variable", "Double"),
                         ("RemDist", "variable", "Double"), ("EngineeringUnits", "property", "EUInformation"),
                         ("EURange", "property", "Range"))
#: Optional children (ModellingRule Optional in the NodeSet) that this server serves; every
#: other entry of CNC_CHILDREN is Mandatory there
OPTIONAL_SERVED = {("CncInterfaceType", "CncTypeName"), ("CncChannelType", "ActMainProgramLine"),
                   ("CncChannelType", "ActProgramLine")}


def mandatory(type_name: str) -> tuple:
    """The Mandatory children of an ObjectType of :data:`CNC_CHILDREN` itself (not its
    supertypes'): ``(BrowseName, kind, DataType, EngineeringUnits)`` each."""
    return tuple(c for c in CNC_CHILDREN.get(type_name, ()) if (type_name, c[0]) not in OPTIONAL_SERVED)


__all__ = ["CNC_NS", "CNC_OBJECT_TYPES", "CNC_ENUMS", "CNC_CHILDREN", "CNC_POSITION_CHILDREN",
           "CNC_POSITION_VARIABLE_TYPE", "CNC_POSITION_DATA_TYPE", "OPTIONAL_SERVED", "mandatory"]
