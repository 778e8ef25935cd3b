"""The wording of each query family: the regular expressions (on lower-case text) that recognise a
clause's family in :data:`ctgpp.language.compiler.families.FAMILIES`, and that some handlers
(:mod:`ctgpp.language.compiler.handlers`) read a side, a bound or a pace from.
"""

from __future__ import annotations

import re

from ctgpp.language.bounds import UP_TO_BOUND
from ctgpp.language.compiler.patterns import NUM

LANE_CHANGE = (
    r"(?:chang|switch|mov|go|shift|merg|get|pull|swing|hop|slid|nip|dart|duck)\w*\s+(?:\w+\s+){0,3}?"
    r"(?:to|into|onto|in)\s+(?:the\s+)?"
    r"(?:left|right)(?:[- ]hand)?\s+lane|lane[- ]change\s+(?:to\s+the\s+)?(?:left|right)"
    r"|chang\w*\s+lanes?\s+(?:to\s+(?:the\s+)?)?(?:left|right)|(?:left|right)\s+lane[- ]change"
    r"|\b(?:mov|shift|go|chang|switch)\w*\s+(?:one\s+|a\s+)?lanes?\s+(?:over\s+)?(?:to\s+(?:the\s+)?)?(?:left|right)"
    r"|\b(?:go|goes|move|moves|get|gets|switch\w*|chang\w*)\s+(?:to\s+)?(?:left|right)\s+lane\b"
    r"|\b(?:chang|switch|mov|shift|merg|pull|go)\w*\s+back\s+(?:in)?to\s+the\s+(?:left|right)\b"
    r"|\bchang\w*\s+to\s+the\s+(?:left|right)\b(?!\s*(?:-?hand\s+)?(?:side\s+)?of\b)"
    r"|\b(?:mov|shift|swing|hop|slid)\w*\s+(?:over\s+)?(?:to\s+the\s+)?(?:left|right)\b"
    r"(?!\s*(?:-?hand\s+)?(?:side\s+)?of\b|\s+(?:turn|at|into\s+the\s+(?:intersection|junction)))"
)

# a turn the next-intersection rule cannot be told: one further on ("at the second intersection")
TURN_LATER = (
    r"\b(?:second|third|fourth|2nd|3rd|4th|last|final)\s+(?:intersection|junction|crossing"
    r"|light|lights|corner|street|road|exit)\b"
)

TURN = (
    r"\bturn\w*\s+(?:to\s+the\s+)?(?:left|right)|\b(?:left|right)\s*-?\s*turn"
    r"|\btak\w*\s+(?:a\s+|the\s+(?:next\s+|first\s+)?)?(?:left|right)"
)

# a U-turn: "makes a U-turn", "does a u turn", "U-turns", "turns around" / "turns round" (a three-point
# turn reverses, and stays refused: refusals.MANOEUVRES)
U_TURN = (
    r"\bu[- ]?turn\w*|\bturn\w*\s+(?:a)?round\b"
    r"|\b(?:head|go|drive|turn|come)\w*\s+back\s+(?:the\s+way|where)\s+(?:it|they|he|she)\s+came"
)

STRAIGHT = r"\b(?:go|goes|going|drive\w*|continu\w*|head\w*|keep\w*\s+going)\s+straight"

SIDE_OF = r"(?:on|to)\s+(?:the\s+)?(?:left|right)(?:[- ]hand)?\s+(?:side\s+)?of\b"

ACCELERATION = re.compile(
    rf"({NUM})\s*(?:m/s²|m/s\^?2|m/s/s|m\s*s-2|(?:meters?|metres?)\s+per\s+second\s+squared)"
)

COLLIDE = (
    r"\bcollid\w*|\bcollision\w*|\bcrash\w*|\bhit\b|\bhits\b|\bsmash\w*|\brams?\b|\bbump\w*\s+into"
    r"|accident|\b(?:come|comes|coming|came)\s+into\s+contact|\b(?:make|makes|making|made)\s+(?:physical\s+)?contact"
    r"|\b(?:run|runs|ran|running|swerv\w*|veer\w*|plow\w*|plough\w*|slam\w*|driv\w*|drove)\s+into\s+"
    r"(?:(?:vehicle|car|agent|truck)\s*#?\d+|v\d+|#\d+|(?:the\s+)?ego)\b"
)

REAR_END = (r"rear[- ]?end|from\s+behind|into\s+the\s+(?:back|rear)\s+of"
            r"|from\s+the\s+(?:back|rear)(?:\s+side)?\b")

CUT_IN = (
    r"\bcut\w*\s+(?:in|off|ahead|in\s+front)\b|\bmerg\w*\s+(?:\w+\s+){0,2}?(?:ahead|in\s+front)\s+of"
    r"|\bsqueez\w*\s+(?:in\s+|into\s+)?(?:ahead|in\s+front)\s+of"
)

# "passes" only with a vehicle after it: "passes within 2 m of (x, y)" is a reach, "pass each other" is
# refused (refusals.MANOEUVRES)
_A_VEHICLE = r"(?:(?:vehicle|car|agent|truck)\s*#?\d+|v\d+|#\d+|(?:the\s+)?ego)\b"
OVERTAKE = (
    rf"\bovert(?:ak|ook)\w*|\bpass(?:es|ed|ing)?\s+(?:by\s+)?{_A_VEHICLE}"
    rf"|\b(?:get|go|drive|move)(?:s|es|ing)?\s+(?:past|around)\s+{_A_VEHICLE}"
)

RIGHTMOST = r"right-?\s?most\s+lane|far(?:thest)?[- ]right\s+lane"

FOLLOW_VEHICLE = r"\bfollow\w*|\btail\w*|\bbehind\b"

SPEED_LIMIT = (
    r"speed\s+limit|exceed|slower\s+than|(?:no|not)\s+(?:faster|quicker|more)\s+than|at\s+most|\bbelow\b"
    rf"|{UP_TO_BOUND}|(?:never|not|n't)\s+(?:go|drive|get)\w*\s+(?:over|above)"
    r"|\bunder\b|max(?:imum)?\s+(?:speed|of)|\blimit\w*|(?:faster|above|over)\s+than|\bcap(?:s|ped|ping)?\b"
)

TARGET_SPEED = (
    r"target\s+speed|(?:drive|travel|go|move|cruise|run|ride|proceed)\w*\s+(?:at|with)|speed\s+of|\bat\s+"
    r"|maintain\w*|hold\w*|keep\w*|speed\w*\s+(?:up|down)|accelerat\w*|slow\w*|decelerat\w*|\bspeed\b"
    r"|\breach\w*|\bget\w*\s+(?:up\s+)?to\b"
    rf"|\b(?:drive|go|travel|move|cruise|ride)\w*\s+(?={NUM}\s*(?:m/s|km/h|kph|mph)\b)"
)

STAY_AWAY = (
    r"away\s+from|at\s+least|(?<!no )(?:more|further|farther)\s+than|keep\w*\s+(?:a\s+)?(?:safe\s+)?distance"
    r"|(?:not|n't|never)\s+(?:get|come|go|drive)\w*\s+(?:too\s+)?(?:close|near|within)|\bavoid\w*\s+"
    r"|minimum\s+(?:distance|separation|gap|spacing|clearance)|\bfar\s+(?:away\s+)?from\b"
    r"|\d\s*(?:m|meters?|metres?|ft|feet)\s+or\s+(?:more|further|farther|greater)\b"
)

WITHIN = (
    r"within|close\s+to|\bnear\b|closer\s+than|less\s+than|no\s+more\s+than|no\s+(?:farther|further)\s+than"
    r"|at\s+most|\bstay\w*\s+with\b|\bstick\w*\s+(?:close\s+)?to\b|\bup\s+to\b|\bunder\b|\bmax(?:imum)?\b"
    r"|\d\s*(?:m|meters?|metres?|ft|feet)\s+or\s+(?:less|closer|under|nearer)\b"
)

# the centre of a lane, which following a lane keeps to (keeping to a lane only stays in it)
LANE_CENTRE = r"\bcent(?:er|re)(?:d|\s*line)?\b|\bmiddle\b"

FOLLOW_LANE = (
    r"follow\w*\s+(?:its|their|his|her|the|a|current)?\s*(?:own\s+|current\s+)?lanes?\b"
    r"|(?:stay|remain)\w*\s+(?:in|within|inside)\s+(?:its|their|the|his|her)?\s*(?:own\s+|current\s+)?lanes?\b"
    r"|lane[- ]following"
    r"|(?:stay|keep|stick|remain|driv)\w*\s+(?:\w+\s+){0,2}?(?:in|to|at|along)\s+the\s+(?:cent(?:er|re)|middle)"
    r"\s+of\s+(?:its|their|the|his|her)\s+(?:own\s+)?lanes?|\bcent(?:er|re|ere)d\s+(?:in|on)\s+(?:its|their|the)\s+(?:own\s+)?lanes?"
    r"|\b(?:stay|keep|stick|remain|driv)\w*\s+(?:to|on|at|along)\s+(?:the|its|their)\s+lane(?:'s)?\s+(?:cent(?:er|re)|middle)"
)

KEEP_LANE = (
    r"\bkeep\w*\s+(?:to\s+)?(?:its|their|his|her|the)\s+(?:own\s+|current\s+)?lanes?\b|lane[- ]keeping"
    r"|(?:not|n't|never)\s+(?:change|switch|leave)\w*\s+(?:its\s+|their\s+)?lanes?"
    r"|\bno\s+(?:lane[- ]chang\w*|chang\w*\s+(?:of\s+)?lanes?)"
)

REACH_BELOW = (
    r"\b(?:slow\w*|decelerat\w*|brak\w*|reduc\w*)\b.*"
    r"(?:\b(?:under|below|less\s+than|at\s+most|no\s+more\s+than)\b|\bor\s+(?:less|lower|slower|under|below)\b)"
    rf"|{NUM}\s*(?:m/s|km/h|kph|mph)\s+or\s+(?:less|lower|slower|under|below)\b"
)

REACH_ABOVE = (
    r"\b(?:speed\w*\s+up|accelerat\w*|get\w*\s+to|reach\w*|pick\w*\s+up)\b.*"
    r"(?:\b(?:over|above|more\s+than|at\s+least|faster\s+than)\b|\bor\s+(?:more|higher|faster|over|above)\b)"
    rf"|{NUM}\s*(?:m/s|km/h|kph|mph)\s+or\s+(?:more|higher|faster|over|above)\b"
)

OFFROAD_STAY = r"(?:stay|remain|keep|drive)\w*\s+on\s+(?:the\s+)?(?:road|drivable|pavement|street)"
# leaving the road, as opposed to staying on it: asked for without a negation, it is no behaviour
LEAVE_ROAD = r"off[- ]?(?:the\s+)?road|leav\w*\s+the\s+(?:road|drivable\s+area)"
OFFROAD = rf"{OFFROAD_STAY}|{LEAVE_ROAD}|drivable\s+area"

STOP = r"\bstop\w*|\bhalt\w*|standstill|\bpark(?:s|ed)?\b|\b(?:come|comes|came|coming)\s+to\s+rest\b"

# the previous clause's behaviour again, for other vehicles: "then vehicle 10 does the same"
SAME_AGAIN = r"\b(?:do|does|did|doing)\s+(?:the\s+same|likewise|so\s+too)\b|\bfollows?\s+suit\b"

# stopped from the start to the end: "stands still", "remains stationary", "stays put", "does not move"
STAND_STILL = (
    r"\bstand\w*\s+still|\b(?:remain|stay)\w*\s+(?:still|put|stationary|motionless|at\s+rest)\b"
    r"|\b(?:not|never|n't)\s+(?:move|budge)\b(?!\s+(?:over|into|in|to|onto|left|right|away|off|past|ahead|forward"
    r"|out|up|back|closer|toward|towards|a\s+lane|lanes?)\b)"
)

# moving from the start to the end: "keeps moving", "keeps going", "does not stop", "never stops"
KEEP_MOVING = (
    r"\bkeep\w*\s+(?:on\s+)?(?:moving|going|driving|rolling)\b|\bwithout\s+stopping\b"
    r"|\b(?:not|never|n't)\s+(?:come\s+to\s+a\s+)?(?:stop|halt)\w*"
)

# setting off: moving at the end, from rest or not ("drives off", "pulls away", "starts moving")
MOVE_OFF = (
    r"\b(?:drive|drives|drove|driving|pull|pulls|pulled|pulling|set|sets|setting|move|moves|moved|moving)\s+"
    r"(?:off|away)\b(?!\s+from\b|[-\s]+(?:the\s+|a\s+)?(?:road|street|pavement|map|edge|kerb|curb|cliff|bridge))"
    r"|\bget\w*\s+(?:going|moving)\b|\bstart\w*\s+(?:moving|driving|to\s+(?:move|drive))\b"
)

# a place on the map a stop may be asked at that the compiler has no coordinates for
STOP_PLACE = (
    r"\b(?:before|at|in|near|after|past|by|behind|in\s+front\s+of)\s+(?:the\s+|a\s+)?(?:next\s+|first\s+)?(?:red\s+)?"
    r"(?:intersection|junction"
    r"|crossing|crosswalk|zebra|stop\s*(?:line|sign)|(?:traffic\s+)?(?:lights?|signals?)|corner|roundabout|kerb|curb"
    r"|exit)"
    r"|\b(?:on|onto|to|at|in|by)\s+(?:the\s+|a\s+)?(?:hard\s+)?(?:shoulder|roadside|verge|side\s+of\s+the\s+road"
    r"|parking\s+(?:spot|space|lot|bay)|driveway|car\s+park)"
)

REACH = (
    r"\breach\w*|\b(?:go|drive|head|move|navigate|travel|get)\w*\s+(?:\w+\s+)?(?:to|towards?)\b|arriv\w*"
    r"|\b(?:send|bring|take|steer|direct|route)\w*\s+(?:\w+\s+){0,3}?(?:to|towards?)\b|\bhead\w*\s+for\b"
    r"|\bgoal\b|destination|waypoint"
)

COMPARE = r"\b(?:faster|quicker|slower|more\s+slowly|more\s+quickly)\s+than\b"

PACE = r"\b(?:fast|quickly|rapidly|speedily|slow|slowly)\b(?!\s+(?:down|up))"

AHEAD = (
    rf"({NUM})\s*(?:m|meters?|metres?|ft|feet)\s+(?:further\s+|farther\s+)?"
    r"(?:ahead|in\s+front|down|along|forward|on|up)\b"
    rf"|\b(?:advanc|progress)\w*\s+(?:another\s+|a\s+further\s+)?({NUM})\s*(?:m|meters?|metres?|ft|feet)\b"
)

# a lower bound on speed said positively, the number right after it ("goes faster than 10 m/s", "drives
# above 30 km/h", "should exceed 8 m/s"): a minimum speed unless the clause is negated ("never exceeds")
LOWER_SPEED = rf"\b(?:faster|quicker)\s+than\s+{NUM}|\b(?:above|over|exceed\w*|more\s+than)\s+{NUM}"

MIN_SPEED = (
    r"\bat\s+least|\bno\s+(?:less|slower)\s+than|\bnot\s+(?:less|slower)\s+than|\bminimum(?:\s+speed)?"
    r"|(?:never|not|n't)\s+(?:drop|go|fall|get|slow|drive|travel|move|be)\w*\s+(?:down\s+)?(?:below|under)"
)

TARGET_DISTANCE = (
    rf"(?:distance|gap|spacing|separation|headway)\s+of\s+(?:about\s+|around\s+|roughly\s+|approximately\s+"
    rf"|exactly\s+)?{NUM}|\b(?:about|around|roughly|approximately|exactly)\s+{NUM}\s*(?:m|meters?|metres?|ft|feet)\b"
    rf"|{NUM}\s*(?:m|meters?|metres?|ft|feet)\s+(?:behind|back\s+from)"
)

BOUND = (  # words that make a distance a bound, not a target
    r"\bat\s+(?:least|most)\b|\bwithin\b|\b(?:less|more|closer|farther|further|nearer)\s+than\b|\bunder\b|\bover\b"
    r"|\bminimum\b|\bmaximum\b|\bmin\b|\bmax\b|\bup\s+to\b|\bbetween\b|\bbeyond\b|\baway\b"
    r"|\bor\s+(?:more|less|fewer|further|farther|closer|greater|higher|lower|over|under)\b"
)
