(.../pcb-gcode-3.6.2.4/pcb-gcode.ulp)
(Copyright 2005 - 2012 by John Johnson)
(See readme.txt for licensing terms.)
(Representative program written by the oga project in the style of pcb-gcode)
(This file generated from the board:)
(.../oga/led_driver.brd)
(Current profile is .../pcb-gcode-3.6.2.4/profiles/mach.pp  )
(This file generated 3/4/17 7:59 PM)
(Settings from pcb-machine.h)
(spindle on time = 0.0000)
(spindle speed = 20000.0000)
(milling depth = -0.0630)
(tool change at 0.0000  0.0000  1.5000  )
(feed rate xy = F12    )
(feed rate z  = F6     )
(Z Axis Settings)
(  High     Up        Down     Drill)
(0.2500  	0.0500  	-0.0030 	-0.0710 )
(Settings from pcb-defaults.h)
(isolate min = 0.0030)
(isolate max = 0.0200)
(isolate step = 0.0025)
(Generated bottom outlines, bottom drill, )
(Unit of measure: inch)
( Tool|       Size       |  Min Sub |  Max Sub |   Count )
( T01 | 0.800mm 0.0315in | 0.0000in | 0.0000in |       0 )
(Inch Mode)
G20
(Absolute Coordinates)
G90
S20000
G00 Z0.2500  
G00 X0.0000  Y0.0000  
M03
G04 P0.000000
G00 Z0.0500  
G00 X0.2500  Y0.3500 
G01 Z-0.0030 F6     
G01 X0.3500  Y0.3500 F12    
G01 X0.3500  Y0.4500 
G01 X0.2500  Y0.4500 
G01 X0.2500  Y0.3500 
G00 Z0.0500  
G00 X0.5500  Y0.3500 
G01 Z-0.0030 F6     
G01 X0.6500  Y0.3500 F12    
G01 X0.6500  Y0.4500 
G01 X0.5500  Y0.4500 
G01 X0.5500  Y0.3500 
G00 Z0.0500  
G00 X0.8500  Y0.3500 
G01 Z-0.0030 F6     
G01 X0.9500  Y0.3500 F12    
G01 X0.9500  Y0.4500 
G01 X0.8500  Y0.4500 
G01 X0.8500  Y0.3500 
G00 Z0.0500  
G00 X0.8500  Y0.7500 
G01 Z-0.0030 F6     
G01 X0.9500  Y0.7500 F12    
G01 X0.9500  Y0.8500 
G01 X0.8500  Y0.8500 
G01 X0.8500  Y0.7500 
G00 Z0.0500  
G00 X0.5500  Y0.7500 
G01 Z-0.0030 F6     
G01 X0.6500  Y0.7500 F12    
G01 X0.6500  Y0.8500 
G01 X0.5500  Y0.8500 
G01 X0.5500  Y0.7500 
G00 Z0.0500  
G00 X0.2500  Y0.7500 
G01 Z-0.0030 F6     
G01 X0.3500  Y0.7500 F12    
G01 X0.3500  Y0.8500 
G01 X0.2500  Y0.8500 
G01 X0.2500  Y0.7500 
G00 Z0.0500  
G00 X0.3500  Y0.4300 
G01 Z-0.0030 F6     
G01 X0.5500  Y0.4300 F12    
G01 X0.5700  Y0.4500 
G01 X0.5700  Y0.7500 
G00 Z0.2500  
M05
G00 Z1.5000  
G00 X0.0000  Y0.0000  
M06 T01  ; 0.0315  
G01 Z0.0000  F6     
M06 
G00 Z0.0500  
M03
G04 P0.000000
G82 X0.3000  Y0.4000  Z-0.0710 F6     R0.0500  P0.250000
G82 X0.6000  Y0.4000  
G82 X0.9000  Y0.4000  
G82 X0.9000  Y0.8000  
G82 X0.6000  Y0.8000  
G82 X0.3000  Y0.8000  
M05
G00 Z1.5000  
G00 X0.0000  Y0.0000  
M02
