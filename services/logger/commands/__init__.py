"""services.logger.commands"""
