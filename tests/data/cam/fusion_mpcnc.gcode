%
(Fusion CAM 2.0.18961)
( Posts processor: MPCNC21.cps)
( Representative program written by the oga project in the style of the MPCNC post)
( Document: oga bracket)
( Setup: top)
( )
( Tools Table:)
(  T1 D=3.175 CR=0 - ZMIN=-3 - flat end mill )
( )
( Feedrate and Scaling Properties:)
(   Feed: Travel speed X/Y = 2500)
(   Feed: Travel Speed Z = 300)
( )
( *** START begin ***)
G90
G21
G92 X0 Y0 Z0
M62 P0
M62 P1
( *** START end ***)
( )
( *** SECTION begin ***)
( 2D Contour1 - Milling - Tool: 1 -  flat end mill)
( COMMAND_START_SPINDLE)
( COMMAND_SPINDLE_CLOCKWISE)
( >>> Spindle Speed 18000)
M3 S18000
( MOVEMENT_PLUNGE)
( First G1 --> G0)
G0 Z3 F300
X25 Y2 F2500
G1 Z0.635 F339
Z-1.5 F339
( MOVEMENT_FINISH_CUTTING)
G17 G2 X22 Y5 I-3 F3048
G1 X9 F3048
G17 G2 X5 Y9 J4 F3048
G1 Y31 F3048
G17 G2 X9 Y35 I4 F3048
G1 X41 F3048
G17 G2 X45 Y31 J-4 F3048
G1 Y9 F3048
G17 G2 X41 Y5 I-4 F3048
G1 X22 F3048
G17 G2 X25 Y2 J-3 F3048
( MOVEMENT_CUTTING)
G1 Z-0.865 F339
Z-3 F339
( MOVEMENT_FINISH_CUTTING)
G17 G2 X22 Y5 I-3 F3048
G1 X9 F3048
G17 G2 X5 Y9 J4 F3048
G1 Y31 F3048
G17 G2 X9 Y35 I4 F3048
G1 X41 F3048
G17 G2 X45 Y31 J-4 F3048
G1 Y9 F3048
G17 G2 X41 Y5 I-4 F3048
G1 X22 F3048
G17 G2 X25 Y2 J-3 F3048
( MOVEMENT_CUTTING)
( Safe G1 --> G0)
G0 Z3 F300
( COMMAND_STOP_SPINDLE)
M5
M63 P1
M63 P0
( *** STOP begin ***)
G0 X0 Y0 F2500
M2
( *** STOP end ***)
%
